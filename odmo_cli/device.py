"""Where tensors live: `--device auto|cpu|cuda|cuda:N|mps` turned into a torch.device, once.

`cpu` is every command's default, so a run that names no device computes exactly as before (the
same seed gives the same bytes). `auto` takes the best one present: the first CUDA GPU, else
Apple's MPS, else the CPU. A device that is absent is a UserError naming the problem and the
valid choices (the CLI: one line, exit 2), raised before any data is read or file written.
"""

from __future__ import annotations

import platform

import torch

from odmo_cli.errors import UserError

CHOICES = "auto, cpu, cuda, cuda:N, mps"


def resolve_device(spec: str | torch.device | None = "cpu") -> torch.device:
    """--device's value -> a torch.device that exists on this machine (None: cpu)."""
    if isinstance(spec, torch.device):
        spec = str(spec)
    text = (spec or "cpu").strip().lower()
    if text == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda", torch.cuda.current_device())
        return torch.device("mps") if _mps_available() else torch.device("cpu")
    if text == "cpu":
        return torch.device("cpu")
    if text == "mps":
        if not _mps_available():
            raise UserError(f"device mps is not available on this machine (no Apple GPU usable by torch); "
                            f"valid: {CHOICES}")
        return torch.device("mps")
    kind, _, index = text.partition(":")
    if kind != "cuda" or (index and not index.isdigit()):
        raise UserError(f"unknown device {spec!r}; valid: {CHOICES}")
    if not torch.cuda.is_available():
        why = "this torch is built without CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
        raise UserError(f"device {text} is not available on this machine ({why}); valid here: auto, cpu")
    count = torch.cuda.device_count()
    n = int(index) if index else torch.cuda.current_device()
    if n >= count:
        raise UserError(f"device {text} is not available: this machine has {count} CUDA GPU(s), "
                        f"cuda:0 to cuda:{count - 1}")
    return torch.device("cuda", n)


def _mps_available() -> bool:
    mps = getattr(torch.backends, "mps", None)
    return bool(mps is not None and mps.is_available())


def describe(device: torch.device) -> str:
    """A device in words, for reports: `cpu (x86_64)`, `cuda:0 (NVIDIA H200)`, `mps`."""
    if device.type == "cuda":
        return f"{device} ({torch.cuda.get_device_name(device)})"
    if device.type == "cpu":
        return f"cpu ({platform.processor() or platform.machine()})"
    return str(device)


def generator(device: torch.device, seed: int) -> torch.Generator:
    """A seeded torch generator on `device` (random draws must come from one on their own device)."""
    return torch.Generator(device=device).manual_seed(seed)


def model_device(model: torch.nn.Module) -> torch.device:
    """The device of a model's first parameter or buffer (cpu for one without any)."""
    for t in model.parameters():
        return t.device
    for t in model.buffers():
        return t.device
    return torch.device("cpu")


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (timings on a GPU measure nothing without it)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()
