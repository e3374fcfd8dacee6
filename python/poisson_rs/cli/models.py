"""``poisson-rs models``: the shipped models and the command that trained each."""

from __future__ import annotations

import argparse
import shlex
from typing import Any

NAME = "models"


def add_parser(sub: Any) -> argparse.ArgumentParser:
    return sub.add_parser(NAME, help="list the shipped models and how they were trained")


def run(args: argparse.Namespace) -> int:
    import json

    from ..integrators import list_models, load_model

    for name in list_models():
        m = load_model(name)
        md = m.metadata
        try:
            recorded = json.loads(md.get("config", "{}"))
        except ValueError:
            recorded = {}
        command = _runnable_command(md.get("command", "?"), recorded, name)
        print(f"{name}: {m!r}\n  command: {command}\n  seed: {md.get('seed', '?')}")
    return 0


def _runnable_command(command: str, recorded: Any, name: str) -> str:
    """The recorded training command as one to run here: ``--out`` a relative ``NAME.safetensors``
    (not the training machine's path), plus the options added since the model was trained whose
    new defaults would train another model."""
    try:
        words = shlex.split(command)
    except ValueError:
        return command
    if words[:2] != ["poisson-rs", "train"]:
        return command
    if "--out" in words[:-1]:
        words[words.index("--out") + 1] = f"{name}.safetensors"
    if isinstance(recorded, dict) and recorded:
        # Recorded before the option existed: trained with nested autograd (the default is now
        # the reverse pass, whose weights end ~1e-14 away) and from a Xavier-uniform network.
        if "derivatives" not in recorded and "--derivatives" not in words:
            words += ["--derivatives", "autograd"]
        if "init" not in recorded and "--init" not in words:
            words += ["--init", "xavier"]
    return shlex.join(words)
