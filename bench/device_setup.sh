# Sourced at the start of every command on the lent GPU machine (which has torch but neither
# warp-lang nor this package installed, and no pyvista/tetgen to mesh the anatomies).
# Here, once:  ../shared/tools/warp-for-device.sh   (makes .devwheels/a and .devwheels/b)
#              python -c "from warpgnn.fem_ref.generate import anatomy_mesh as a; [a('.devdata', f'L{i}') for i in range(1, 6)]"
#              echo /.devdata/ >> .git/info/exclude
# There: call 1 carries .devwheels/a and runs  mkdir -p /opt/dw && cp .devwheels/a/* /opt/dw/
#   (a call carries at most 64 MiB with the working tree; once the tree passed ~18 MB, split
#   .devwheels/a/warp.part.00 in two with split -b 23592960 into .devwheels/a1, a2 and carry them in
#   two calls: cp a1/wp.00 /opt/dw/, then cat /opt/dw/wp.00 a2/wp.01 > /opt/dw/warp.part.00)
#        call 2 carries .devwheels/b and .devdata and starts with  source bench/device_setup.sh
#   (bench/results, ~190 MB by 2026-11-26, travels with the tree and is not needed there: once the tree plus
#   .devwheels/b pass 64 MiB, move bench/results aside for the device calls and back after)
# A machine is given back 30 s after a call ends: make every call copy what must survive
# (checkpoints, logs) into $OUT (bench/wait_runs.sh RUNS SECONDS $OUT does; given DATA too, it also
# evaluates each run as it finishes, into RUNS/.eval), and chain long runs with setsid + bench/wait_runs.sh.
# A machine also goes back once held 30 minutes, unless a call is then in flight (that call
# finishes): a 30-minute run plus setup outlasts that, so time the last wait to start less than
# 10 minutes before the run ends (e.g. a short wait in between); otherwise resume it from $OUT's
# last.pt on a fresh machine (its recompilation is not charged to --time-budget).
# To start a run once another has finished (a GPU freed mid-call), wait in a setsid'd shell on the training
# process itself: pgrep -f 'warpgnn(.cli)? train.*NAME' with a bracket in NAME (e.g. revq_s[2]), so that the
# waiting shell's own pattern does not match. Matching the run's name alone also matches the device call's own
# command line (its train_paper.sh regex holds the name): on 2026-11-26 such a wait lasted until the call ended.
# The same for any script the call itself names: `while pgrep -f eval_paper` in a call that starts eval_paper.sh waited
# out its whole limit (2026-11-26, 500 s of device time); run such a script in the foreground, or wait on its pid.
# Resuming a 12-pass run (last.pt 30 MB, best.pt 10 MB) costs no extra call: put best.pt, log.csv and
# stdout.txt under an ignored .devout_a/runs/<run>/ and last.pt under .devout_b/runs/<run>/, carry
# .devout_a with a1 and .devout_b with a2, and cp -r each one's runs/* into the RUNS folder.
set -e
[ -e warpgnn/fem_ref ] || ln -s ../fem_ref warpgnn/fem_ref; [ -e warpgnn/kernels ] || ln -s ../kernels warpgnn/kernels
if [ ! -d /opt/site/warp ]; then
  mkdir -p /opt/site && cat /opt/dw/warp.part.* .devwheels/b/warp.part.* | xz -d -T0 | tar -x -C /opt/site
  python3 -m pip install -q --no-deps --no-index --target /opt/site .devwheels/b/*.whl
fi
export PYTHONPATH=/opt/site:$PWD PYTHONUNBUFFERED=1 NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
mkdir -p /opt/bin && printf '#!/bin/sh\nexec python3 -m warpgnn.cli "$@"\n' > /opt/bin/warpgnn && chmod +x /opt/bin/warpgnn
export PATH=/opt/bin:$PATH
mkdir -p /opt/data/anatomies && cp -n .devdata/anatomies/*.vtu /opt/data/anatomies/ 2>/dev/null || true
# torch.compile's cache from an earlier session, if carried (ignored .devcache/inductor.tgz): a 12-pass run's first
# epoch took 192 s on a fresh machine and 48 s on the machine that had compiled its twin (2026-11-26; what a carried
# cache saves on a fresh machine is unmeasured). Pack it at a session's end with
# tar -C /tmp -czf $OUT/inductor.tgz torchinductor_root (size unmeasured: carry it only if it fits beside the rest)
if [ -f .devcache/inductor.tgz ] && [ ! -d /tmp/torchinductor_root ]; then
  tar -C /tmp -xzf .devcache/inductor.tgz || { echo "device_setup: inductor cache not unpacked" >&2; rm -rf /tmp/torchinductor_root; }
fi
set +e
