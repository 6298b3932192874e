"""Where a world model fits and predicts: the config's ``device`` resolved to a torch device."""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """``device`` of the config: ``cpu``, ``cuda[:N]``, or ``auto`` (a GPU when there is one).

    It places the world model (its fit and its predictions); the policy, the critic and the
    robots stay on the CPU, where their small networks run fastest next to the physics.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, TypeError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device={name!r} but torch sees no CUDA GPU here; use device=cpu or device=auto")
    return device
