"""Checkpoints: written atomically (temporary name, fsync, rename), read with one-line errors
for what goes wrong in practice (missing, truncated or foreign file, NaN weights)."""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path

import torch

from .errors import InputError
from .model import TIGNN, ModelConfig

# The network shipped with the package: the 5-pass hybrid of our best recipe (pushforward, additive
# velocity noise, --rotate, the velocity take-back of smooth displacements), 30 minutes on H200s; seed 1,
# the best validation of three, of bench/results/gnn_smooth_vel1800_s12_h200.json
PRETRAINED_HYBRID = Path(__file__).with_name("weights") / "hybrid_p5_takeback.pt"


def save_atomically(payload: dict, path) -> None:
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        torch.save(payload, fh)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def model_payload(model: TIGNN, **extra) -> dict:
    return {"model_config": asdict(model.config), "model": model.state_dict(), **extra}


def read(path, map_location="cpu") -> dict:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # torch raises RuntimeError, EOFError, UnpicklingError... on bad files
        raise InputError(f"checkpoint {path} is truncated or corrupt ({type(exc).__name__})") from None
    if not isinstance(payload, dict) or "model_config" not in payload or "model" not in payload:
        raise InputError(f"{path} is not a warpgnn checkpoint")
    for name, value in payload["model"].items():
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise InputError(f"checkpoint {path} holds NaN or infinite values in {name}")
    return payload


def load_model(path, device="cpu") -> tuple[TIGNN, dict]:
    payload = read(path, map_location=device)
    try:
        model = TIGNN(ModelConfig(**payload["model_config"]))
        model.load_state_dict(payload["model"])
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"checkpoint {path} does not match this warpgnn's model: {str(exc).splitlines()[0]}") from None
    return model.to(device).eval(), payload
