"""Checkpoints: written atomically (temporary name, fsync, rename), read with one-line errors
for what goes wrong in practice (missing, truncated or foreign file, NaN weights)."""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path

import torch

from .errors import InputError
from .model import TIGNN, ModelConfig

# The network shipped with the package: the 5-pass hybrid of the best recipe (training.RECIPES), seed 1 of
# the record bench/results/gnn_smooth_vel1800_s12_h200.json
PRETRAINED_HYBRID = Path(__file__).with_name("weights") / "hybrid_p5_takeback.pt"
# ModelConfig options removed in issue 55 (their code is last in commit ae2f903), at the values that give
# today's model: a checkpoint holding one at that value loads, at any other it is refused
REMOVED_OPTIONS = {"rate_weights": (1.0, 1.0, 1.0), "tip_weight": 1.0, "imposed_in_loss": True,
                   "operator_activation": "none", "reversible_positions": False, "reversible_velocities": False,
                   "dissipation_init_scale": 0.05, "decoder_hidden_layers": None, "split_decoders": False,
                   "local_positions": False, "state_skip": False}


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
    except Exception as exc:  # noqa: BLE001 (torch raises RuntimeError, EOFError, UnpicklingError... on bad files)
        raise InputError(f"checkpoint {path} is truncated or corrupt ({type(exc).__name__})") from None
    if not isinstance(payload, dict) or "model_config" not in payload or "model" not in payload:
        raise InputError(f"{path} is not a warpgnn checkpoint")
    for name, value in payload["model"].items():
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise InputError(f"checkpoint {path} holds NaN or infinite values in {name}")
    return payload


def model_config(saved: dict, path) -> ModelConfig:
    """The ModelConfig of a checkpoint's saved ``model_config``, removed options at their neutral values dropped."""
    for name in REMOVED_OPTIONS.keys() & saved.keys():
        value = saved[name]
        if (tuple(value) if isinstance(value, list) else value) != REMOVED_OPTIONS[name]:
            raise InputError(f"checkpoint {path} was trained with {name} = {value!r}, an option removed from "
                             "warpgnn (last in commit ae2f903)")
    try:
        return ModelConfig(**{k: v for k, v in saved.items() if k not in REMOVED_OPTIONS})
    except (TypeError, ValueError) as exc:
        raise InputError(f"checkpoint {path} does not match this warpgnn's model: {exc}") from None


def load_model(path, device="cpu") -> tuple[TIGNN, dict]:
    payload = read(path, map_location=device)
    model = TIGNN(model_config(payload["model_config"], path))
    try:
        model.load_state_dict(payload["model"])
    except RuntimeError as exc:
        raise InputError(f"checkpoint {path} does not match this warpgnn's model: {str(exc).splitlines()[0]}") from None
    return model.to(device).eval(), payload
