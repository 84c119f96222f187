# Sourced at the start of every command on a lent GPU machine, which has torch but neither warp-lang nor this
# package installed, and no pyvista/tetgen to mesh the anatomies (a machine's calls share no environment).
# A 4-GPU machine costs the same device time as one: run independent jobs side by side, one a GPU.
# Here, once: ../shared/tools/warp-for-device.sh (makes .devwheels/a and .devwheels/b),
# echo /.devdata/ >> .git/info/exclude, and
# python -c "from warpgnn.fem_ref.generate import anatomy_mesh as a; [a('.devdata', f'L{i}') for i in range(1, 6)]"
# There: call 1 carries .devwheels/a and runs  mkdir -p /opt/dw && cp .devwheels/a/* /opt/dw/
#        call 2 carries .devwheels/b and .devdata and starts with  source bench/device_setup.sh
#   (a call carries at most 64 MiB with the working tree: split a wheel part with split -b over two calls if not)
# Make call 2 at once after call 1 (the machine goes back 30 s after a call; a fresh one cost 50-330 s of device time
# here, the most when H100s were asked for and did not come: name the kind the last reply gave, e.g. nvidia-h200-x4).
# A machine is given back soon after a call ends, and after 30 minutes held: make every call copy what must
# survive (checkpoints, logs) into $OUT (bench/wait_runs.sh RUNS SECONDS $OUT [DATA] does, evaluating each run as
# it finishes), and resume a cut-off run from its last.pt on a fresh machine (`warpgnn train --resume`).
# To start a run once another has finished, wait in a setsid'd shell on the training process itself:
# pgrep -f 'warpgnn(.cli)? train.*NAME' with a bracket in NAME (e.g. hybrid_p5_s[2]), so that neither the waiting
# shell's own pattern nor the call's command line (whose train_paper.sh regex holds NAME) matches.
set -e
[ -e warpgnn/fem_ref ] || ln -s ../fem_ref warpgnn/fem_ref; [ -e warpgnn/kernels ] || ln -s ../kernels warpgnn/kernels
if [ ! -d /opt/site/warp ]; then
  mkdir -p /opt/site && cat /opt/dw/warp.part.* .devwheels/b/warp.part.* | xz -d -T0 | tar -x -C /opt/site
  python3 -m pip install -q --no-deps --no-index --target /opt/site .devwheels/b/*.whl
fi
export PYTHONPATH=/opt/site:$PWD PYTHONUNBUFFERED=1
export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1  # no NVLink multicast
mkdir -p /opt/bin && printf '#!/bin/sh\nexec python3 -m warpgnn.cli "$@"\n' > /opt/bin/warpgnn
chmod +x /opt/bin/warpgnn
export PATH=/opt/bin:$PATH
mkdir -p /opt/data/anatomies && cp -n .devdata/anatomies/*.vtu /opt/data/anatomies/ 2>/dev/null || true
# Modules built here ahead of time (python -m warpgnn.kernels.precompile --arch 90 --out .devdata/aot/NAME, xz'd), put
# where Warp's cache looks (CACHE/<module id>/<module id>.sm90.cubin and .meta), so that no process there compiles
# one (150 s each). A process that builds several tile shapes may still compile all but its first (docs/kernels.md).
for meta in .devdata/aot/*/*.meta; do
  [ -e "$meta" ] || break
  id=$(basename "$meta" .meta); dir=$HOME/.cache/warp/1.19.0/$id; mkdir -p "$dir"; cp "$meta" "$dir/"
  for c in "$(dirname "$meta")/$id".*.cubin.xz; do [ -e "$c" ] && xz -dc "$c" > "$dir/$(basename "$c" .xz)"; done
done
# torch.compile's cache from an earlier session, if carried (ignored .devcache/inductor.tgz; a 12-pass run's first
# epoch took 192 s on a fresh machine, 48 s with its cache): pack it with
# tar -C /tmp -czf $OUT/inductor.tgz torchinductor_root
if [ -f .devcache/inductor.tgz ] && [ ! -d /tmp/torchinductor_root ] && ! tar -C /tmp -xzf .devcache/inductor.tgz; then
  echo "device_setup: inductor cache not unpacked" >&2; rm -rf /tmp/torchinductor_root
fi
set +e
