"""Torch devices by name: the one check every ``device=`` argument goes through, and "auto".

"auto" is CUDA when torch sees a device and the CPU otherwise. It is resolved once, where a
configuration is made, so what a run records names the device it used.
"""

from __future__ import annotations

from typing import Any

#: The device name that picks CUDA when torch sees one, else the CPU.
AUTO_DEVICE = "auto"


def auto_device() -> str:
    """ "cuda" when torch sees a CUDA device, else "cpu"."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def check_device(device: Any, *, instead: str = "use device='cpu'") -> Any:
    """``device`` as a ``torch.device`` ("cpu", "cuda", "cuda:1", or a torch.device).

    TypeError for a non-string, ValueError naming 'device' for any other name, and for CUDA
    where torch sees none or fewer devices than the index asks (before any work). ``instead``
    completes the no-CUDA message with what the caller can do."""
    import torch

    if not isinstance(device, (str, torch.device)):
        raise TypeError(f"device must be a string such as 'cuda' or 'cpu', got {device!r}")
    try:
        dev = torch.device(device)
    except (RuntimeError, ValueError):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {device!r}: torch sees no CUDA device here; {instead}")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(
                f"device {device!r}: torch sees {torch.cuda.device_count()} CUDA device(s)"
            )
    return dev
