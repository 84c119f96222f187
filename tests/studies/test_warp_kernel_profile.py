"""bench/studies/warp_kernel_profile.py on a GPU: every kernel of a hybrid step is timed once per launch, the
passes' kernels once per pass (its H100 run is bench/results/warp_kernel_profile_h100.json)."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
import warp as wp

STUDY = Path(__file__).resolve().parents[2] / "bench" / "studies" / "warp_kernel_profile.py"


@pytest.mark.skipif(wp.get_cuda_device_count() == 0, reason="needs a CUDA device (Warp's kernel timer)")
def test_each_kernel_timed_per_launch(tmp_path):
    pytest.importorskip("tetgen")  # the study meshes L5 itself without --mesh
    out = tmp_path / "profile.json"
    subprocess.run([sys.executable, str(STUDY), "--latent", "16", "--cases", "hybrid:3:1", "--calls", "2",
                    "--json", str(out), "--device", "test", "--command", "test"], check=True)
    kernels = json.loads(out.read_text())["cases"][0]["kernels"]
    per_forward = {name: k["per_forward"] for name, k in kernels.items()}  # the raw features in the encoder, the
    assert per_forward == {"encode": 1, "edge_pass": 3, "node_pass": 3, "hybrid_step": 1}  # tail in the decoder
    assert all(k["mean_us"] > 0 for k in kernels.values())
