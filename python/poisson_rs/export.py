"""Model files: a generating function and its provenance in one safetensors file.

Layout (all tensors float64 except ``poly.powers``, int64), for a system on g* ≅ Rⁿ:

- ``algebra.structure_constants`` (n, n, n): c[i, j, k] with [e_i, e_j] = Σ_k c[i, j, k] e_k;
- ``poly.powers`` (m, 1 + n), rows (k, e₁, …, e_n) for t^k p₁^e₁ ⋯ p_n^e_n; ``poly.coeffs`` (m,);
- ``mlp.{i}.weight`` (out, in), ``mlp.{i}.bias`` (out,): inputs (t, p₁, …, p_n), tanh between
  layers, one output; input and output scales are folded in.

Metadata (strings; JSON where structured): ``format``, ``chart``, ``mlp_power``, ``mlp_inputs``,
``widths``, ``taylor_order``, ``system`` (the system's ``to_dict()``: algebra, Hamiltonian and
parameters, so :func:`poisson_rs.load_model` rebuilds it), ``inertia`` (rigid bodies), ``h_max``,
``domain``, ``final_loss``, ``command``, ``seed``, ``train_seconds``, ``package_version``,
``name``. Files written before other systems existed say ``system = "rigid_body"`` and give the
body by ``inertia``; they still load.

A ``structure`` metadata key names what the generating function lives on: absent or
``lie_poisson`` for the layout above, ``log_canonical`` for a log-canonical model
(:mod:`poisson_rs.realizations.log_canonical_hj`, read by :func:`parse_log_canonical_metadata`),
``polynomial`` for a model on the order-n realization of a polynomial bivector
(:mod:`poisson_rs.realizations.polynomial_hj`, read by its ``read_model_file``).
"""

from __future__ import annotations

import json
import math
import os
import re
import stat
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .files import atomic_write_bytes
from .structures.lie_poisson import LiePoissonSystem, RigidBody
from .untrusted import InputError, parsing

if TYPE_CHECKING:
    from .generating import GeneratingFunction

# Kept free of torch at import time: loading a model to step it in Rust needs no torch.
_CHARTS = ("cayley", "exp")

FORMAT = "poisson_rs.generating/1"
PACKAGE_VERSION = "0.1.0"
_REQUIRED = ("format", "chart", "mlp_power", "widths", "system", "h_max", "domain")

#: Kinds of training domain a model file may record ("all": no domain, e.g. a Taylor model).
DOMAIN_KINDS = ("cube", "shell", "top", "all")


def resolve_system(
    system: LiePoissonSystem | None, inertia: Sequence[float] | None
) -> LiePoissonSystem:
    """The system a writer was given: ``system``, or the rigid body of ``inertia`` (one of the two,
    not both)."""
    if (system is None) == (inertia is None):
        raise TypeError("give exactly one of system and inertia")
    if system is None:
        return RigidBody(tuple(inertia))  # type: ignore[arg-type]
    if not isinstance(system, LiePoissonSystem):
        raise TypeError(f"system must be a LiePoissonSystem, got {type(system).__name__}")
    return system


def model_bytes(
    *,
    powers: np.ndarray,
    coeffs: np.ndarray,
    layers: Sequence[tuple[np.ndarray, np.ndarray]],
    mlp_power: int,
    chart: str,
    system: LiePoissonSystem | None = None,
    inertia: Sequence[float] | None = None,
    mlp_inputs: str = "t,p",
    h_max: float,
    domain: Mapping[str, Any],
    taylor_order: int = 0,
    record: Mapping[str, Any] | None = None,
) -> bytes:
    """The bytes of a model file: polynomial terms, MLP layers (weight (out, in), bias (out,)),
    the system's structure constants and metadata. ``system`` (or, for a rigid body, its
    ``inertia``) names what the model integrates. ``record`` holds provenance (final_loss,
    command, seed, train_seconds, name, ...); non-string values are stored as JSON.
    """
    system = resolve_system(system, inertia)
    tensors: dict[str, np.ndarray] = {
        "algebra.structure_constants": np.ascontiguousarray(system.algebra.c, dtype=np.float64)
    }
    if len(coeffs):
        tensors["poly.powers"] = np.ascontiguousarray(powers, dtype=np.int64)
        tensors["poly.coeffs"] = np.ascontiguousarray(coeffs, dtype=np.float64)
    for i, (w, b) in enumerate(layers):
        tensors[f"mlp.{i}.weight"] = np.ascontiguousarray(w, dtype=np.float64)
        tensors[f"mlp.{i}.bias"] = np.ascontiguousarray(b, dtype=np.float64)
    meta: dict[str, str] = {
        "format": FORMAT,
        "chart": chart,
        "mlp_power": str(int(mlp_power)),
        "mlp_inputs": mlp_inputs,
        "widths": json.dumps([int(w.shape[0]) for w, _ in layers[:-1]]),
        "taylor_order": str(int(taylor_order)),
        "system": json.dumps(system.to_dict()),
        "h_max": repr(float(h_max)),
        "domain": json.dumps(dict(domain)),
        "package_version": PACKAGE_VERSION,
    }
    for k, v in (record or {}).items():
        meta[k] = v if isinstance(v, str) else json.dumps(v, sort_keys=True)
    if system.file_inertia is not None:
        meta["inertia"] = json.dumps([float(i) for i in system.file_inertia])
    return safetensors_bytes(tensors, meta)


_DTYPES = {np.dtype("<f8"): "F64", np.dtype("<i8"): "I64"}


def safetensors_bytes(tensors: Mapping[str, np.ndarray], metadata: Mapping[str, str]) -> bytes:
    """A safetensors file, byte for byte the same for the same tensors and metadata: the header
    is JSON with sorted keys and no spaces, the data in sorted tensor order (the library's own
    writer keeps the metadata in a hash map, whose order changes from run to run).

    Layout: an 8-byte little-endian header length, the header padded with spaces to a multiple
    of 8 bytes, then each tensor's little-endian bytes at its ``data_offsets``."""
    header: dict[str, Any] = {"__metadata__": dict(sorted(metadata.items()))}
    chunks: list[bytes] = []
    offset = 0
    for name in sorted(tensors):
        arr = np.ascontiguousarray(tensors[name])
        dtype = _DTYPES.get(arr.dtype.newbyteorder("<"))
        if dtype is None:
            raise TypeError(f"tensor {name!r} has dtype {arr.dtype}; float64 or int64 expected")
        data = arr.astype(arr.dtype.newbyteorder("<"), copy=False).tobytes()
        header[name] = {
            "dtype": dtype,
            "shape": list(arr.shape),
            "data_offsets": [offset, offset + len(data)],
        }
        chunks.append(data)
        offset += len(data)
    text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return len(text).to_bytes(8, "little") + text + b"".join(chunks)


def read_tensor(data: bytes, name: str) -> np.ndarray | None:
    """One tensor of a safetensors file's bytes (already validated by the core), without
    decoding the others; None when the file has no tensor ``name``."""
    with parsing("model file", name):
        size = int.from_bytes(data[:8], "little")
        header = json.loads(data[8 : 8 + size])
        entry = header.get(name)
        if entry is None:
            return None
        dtype = {"F64": "<f8", "I64": "<i8"}[entry["dtype"]]
        a, b = entry["data_offsets"]
        base = 8 + size
        return np.frombuffer(data[base + a : base + b], dtype=dtype).reshape(entry["shape"])


def tensor_shapes(data: bytes) -> dict[str, list[int]]:
    """The shape of every tensor of a safetensors file's bytes (already validated by the
    core), from its header alone."""
    with parsing("model file", "header"):
        size = int.from_bytes(data[:8], "little")
        header = json.loads(data[8 : 8 + size])
        return {
            str(k): [int(s) for s in v["shape"]] for k, v in header.items() if k != "__metadata__"
        }


def check_widths(data: bytes, widths: Sequence[int], source: str) -> None:
    """InputError naming ``source`` and ``widths`` unless the metadata's hidden widths are
    those of the file's ``mlp.{i}.weight`` tensors (none: no network)."""
    shapes = tensor_shapes(data)
    n_layers = sum(1 for k in shapes if k.startswith("mlp.") and k.endswith(".weight"))
    held = [shapes[f"mlp.{i}.weight"][0] for i in range(n_layers - 1)]
    with parsing(source, "widths"):
        if list(widths) != held:
            raise ValueError(f"metadata 'widths' says {list(widths)} but the tensors hold {held}")


#: Largest relative difference between a file's exact polynomial terms and those derived again
#: from its metadata: both come from the same rationals rounded to float64 once.
EXACT_TERMS_RTOL = 1e-10


def terms_agree(
    found: tuple[np.ndarray, np.ndarray], expected: tuple[np.ndarray, np.ndarray]
) -> bool:
    """Whether two term tables (keys (M, k) int rows, coefficients (M,)) are one polynomial to
    :data:`EXACT_TERMS_RTOL` of its largest coefficient, whatever the row order and however
    repeated keys are split (absent rows count as zero)."""

    def as_map(keys: np.ndarray, coeffs: np.ndarray) -> dict[tuple[int, ...], float]:
        out: dict[tuple[int, ...], float] = {}
        rows = np.asarray(keys).reshape(len(coeffs), -1).tolist() if len(coeffs) else []
        for row, v in zip(rows, np.asarray(coeffs).tolist(), strict=True):
            out[tuple(row)] = out.get(tuple(row), 0.0) + float(v)
        return out

    a, b = as_map(*found), as_map(*expected)
    scale = max((abs(v) for v in (*a.values(), *b.values())), default=0.0)
    worst = max((abs(a.get(k, 0.0) - b.get(k, 0.0)) for k in a.keys() | b.keys()), default=0.0)
    return worst <= EXACT_TERMS_RTOL * scale  # NaN fails


def _check_finite_model(s_fn: GeneratingFunction, path: str | os.PathLike[str]) -> None:
    """ValueError when a coefficient or weight is NaN or infinite (a diverged training run):
    such a file would only be refused when loaded."""
    arrays = [s_fn.coeffs.detach().cpu().numpy()]
    arrays += [a for layer in s_fn.exported_layers() for a in layer]
    if not all(np.isfinite(a).all() for a in arrays):
        raise ValueError(
            f"the model has NaN or infinite weights (training diverged?); {path} not written"
        )


def save_model(
    s_fn: GeneratingFunction,
    path: str | os.PathLike[str],
    *,
    system: LiePoissonSystem | None = None,
    inertia: Sequence[float] | None = None,
    h_max: float,
    domain: Mapping[str, Any],
    taylor_order: int = 0,
    record: Mapping[str, Any] | None = None,
) -> Path:
    """Writes a torch generating function to ``path`` atomically (never a half-written file)."""
    _check_finite_model(s_fn, path)
    data = model_bytes(
        powers=s_fn.powers.cpu().numpy(),
        coeffs=s_fn.coeffs.detach().cpu().numpy(),
        layers=s_fn.exported_layers(),
        mlp_power=s_fn.mlp_power,
        mlp_inputs=s_fn.inputs,
        chart=s_fn.chart,
        system=system,
        inertia=inertia,
        h_max=h_max,
        domain=domain,
        taylor_order=taylor_order,
        record=record,
    )
    # Beside the target, then renamed; only over a regular file (not a device, FIFO or link).
    return atomic_write_bytes(path, data)


def _read_widths(source: str, raw: Mapping[str, str], meta: dict[str, Any]) -> None:
    """meta["widths"]: the MLP's layer widths, a list of positive integers."""
    with parsing(source, "widths"):
        widths = _json(raw, "widths")
        if not isinstance(widths, list) or not all(
            isinstance(w, int) and not isinstance(w, bool) and w > 0 for w in widths
        ):
            raise ValueError(f"metadata 'widths' must be a list of positive integers: {widths!r}")
        meta["widths"] = tuple(widths)


def _read_taylor_order(source: str, raw: Mapping[str, str], meta: dict[str, Any]) -> None:
    """meta["taylor_order"]: the order of the exact Taylor terms (0 when not recorded)."""
    with parsing(source, "taylor_order"):
        meta["taylor_order"] = (
            _int(raw, "taylor_order", 0, _MAX_ORDER) if "taylor_order" in raw else 0
        )


def _json(meta: Mapping[str, str], key: str) -> Any:
    """The JSON value of metadata ``key`` (the caller runs it inside :func:`parsing`)."""
    value = meta[key]
    if not isinstance(value, str):
        raise TypeError(f"metadata '{key}' must be a string, got {type(value).__name__}")
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        raise ValueError(f"metadata '{key}' is not valid JSON: {value[:80]!r}") from None


#: Numbers in metadata, in ASCII only: float() and int() also accept other scripts' digits
#: ("٣" is 3) and underscores, which no writer of the format produces.
_FLOAT_TEXT = re.compile(r"[+-]?((\d+\.?\d*|\.\d+)([eE][+-]?\d+)?|inf|infinity|nan)", re.A | re.I)
_INT_TEXT = re.compile(r"[+-]?\d+", re.A)


def _float(raw: Mapping[str, str], key: str) -> float:
    text = raw[key].strip()
    if not _FLOAT_TEXT.fullmatch(text):
        raise ValueError(f"metadata '{key}' is not a number in ASCII decimal: {raw[key][:40]!r}")
    return float(text)


def _int(raw: Mapping[str, str], key: str, low: int, high: int) -> int:
    text = raw[key].strip()
    if not _INT_TEXT.fullmatch(text) or len(text) > 20:
        raise ValueError(f"metadata '{key}' is not an integer in ASCII decimal: {raw[key][:40]!r}")
    value = int(text)
    if not low <= value <= high:
        raise ValueError(f"metadata '{key}' must lie in {low}..{high}, got {value}")
    return value


#: Largest Taylor order and MLP power a model file may state (the core caps powers at 64).
_MAX_ORDER = 64


def parse_metadata(raw: Mapping[str, str], source: str = "model metadata") -> dict[str, Any]:
    """Checks a model file's metadata and decodes it. Any problem, whatever its kind (nested
    JSON, a malformed number, an odd type), raises one :class:`~poisson_rs.untrusted.InputError`
    (a ValueError) naming ``source`` and the field."""
    with parsing(source):
        if not isinstance(raw, Mapping):
            raise TypeError(f"metadata must be a mapping of strings, got {type(raw).__name__}")
        missing = [k for k in _REQUIRED if k not in raw]
        if missing:
            raise ValueError(f"model metadata lacks {', '.join(missing)}")
        bad = [k for k, v in raw.items() if not (isinstance(k, str) and isinstance(v, str))]
        if bad:
            raise TypeError(f"metadata keys and values must be strings: {bad[:3]!r}")
    with parsing(source, "format"):
        if raw["format"] != FORMAT:
            raise ValueError(f"model format is {raw['format'][:80]!r}, expected {FORMAT!r}")
    meta: dict[str, Any] = dict(raw)
    with parsing(source, "chart"):
        if raw["chart"] not in _CHARTS:
            raise ValueError(f"unknown chart {raw['chart'][:40]!r}; expected one of {_CHARTS}")
    inertia: tuple[float, ...] | None = None
    if "inertia" in raw:
        with parsing(source, "inertia"):
            values = _json(raw, "inertia")
            if (
                not isinstance(values, list)
                or len(values) != 3
                or not all(
                    isinstance(v, (int, float))
                    and not isinstance(v, bool)
                    and math.isfinite(v)
                    and v > 0
                    for v in values
                )
            ):
                raise ValueError(
                    f"metadata 'inertia' must be 3 positive numbers, got {raw['inertia'][:80]!r}"
                )
            inertia = tuple(float(v) for v in values)
    with parsing(source, "system"):
        if raw["system"] == "rigid_body":
            # Written before other systems existed: the body is given by its inertia.
            if inertia is None:
                raise ValueError("model metadata lacks inertia")
            meta["system"] = RigidBody(inertia)  # type: ignore[arg-type]
        else:
            spec = _json(raw, "system")
            if not isinstance(spec, dict):
                raise ValueError(
                    f"metadata 'system' must describe a system, got {raw['system'][:80]!r}"
                )
            try:
                meta["system"] = LiePoissonSystem.from_dict(spec)
            except InputError as e:  # named after the metadata, not the inner dictionary
                raise InputError(source, "system", e.problem) from None
    with parsing(source, "inertia"):
        recorded = meta["system"].file_inertia
        if recorded is not None:
            if inertia is not None and inertia != recorded:
                raise ValueError(
                    f"metadata 'inertia' {list(inertia)} disagrees with 'system' {meta['system']!r}"
                )
            meta["inertia"] = recorded
        elif inertia is not None:
            raise ValueError(f"metadata 'inertia' given for {meta['system']!r}, not a rigid body")
    with parsing(source, "h_max"):
        meta["h_max"] = _float(raw, "h_max")
        if not meta["h_max"] > 0:
            raise ValueError(f"metadata 'h_max' must be a positive number, got {raw['h_max']!r}")
        if math.isinf(meta["h_max"]) and raw["h_max"].strip().lower() not in ("inf", "+inf"):
            # "1e400" overflows to inf, which would turn the strict step-size check off.
            raise ValueError(f"metadata 'h_max' overflows float64: {raw['h_max']!r}")
    with parsing(source, "mlp_power"):
        meta["mlp_power"] = _int(raw, "mlp_power", 0, _MAX_ORDER)
    _read_taylor_order(source, raw, meta)
    _read_widths(source, raw, meta)
    with parsing(source, "domain"):
        domain = _json(raw, "domain")
        if not isinstance(domain, dict) or domain.get("kind") not in DOMAIN_KINDS:
            raise ValueError(
                f"metadata 'domain' must be a cube, a shell, a top or all: {raw['domain'][:80]!r}"
            )
        meta["domain"] = domain
    for key in ("final_loss", "seed", "train_seconds"):
        if key in raw:
            with parsing(source, key):
                meta[key] = _json(raw, key)
    return meta


def load_generating(
    tensors: Mapping[str, np.ndarray], meta: Mapping[str, Any]
) -> GeneratingFunction:
    """Rebuilds the torch generating function from a model file's tensors (already validated by
    the core) and decoded metadata.

    Checks that the tensors agree with the metadata (layer widths), raising ValueError if not.
    """
    import torch

    from .generating import GeneratingFunction

    n_layers = sum(1 for k in tensors if k.endswith(".weight"))
    widths = tuple(int(tensors[f"mlp.{i}.weight"].shape[0]) for i in range(n_layers - 1))
    if n_layers and widths != tuple(meta["widths"]):
        raise ValueError(
            f"metadata 'widths' says {list(meta['widths'])} but the tensors hold {list(widths)}"
        )
    if not n_layers and meta["widths"]:
        raise ValueError(f"metadata 'widths' says {list(meta['widths'])} but there is no MLP")
    system: LiePoissonSystem = meta["system"]
    s_fn = GeneratingFunction(
        widths,
        mlp_power=meta["mlp_power"] if n_layers else 1,
        powers=tensors.get("poly.powers"),
        coeffs=tensors.get("poly.coeffs"),
        chart=meta["chart"],
        inputs=meta.get("mlp_inputs", "t,p"),
        algebra=system.algebra,
    )
    with torch.no_grad():
        for i, layer in enumerate(s_fn.linears):
            layer.weight.copy_(torch.from_numpy(tensors[f"mlp.{i}.weight"]))
            layer.bias.copy_(torch.from_numpy(tensors[f"mlp.{i}.bias"]))
    return s_fn.eval()


#: Values of a model file's ``structure`` metadata (``lie_poisson`` where the key is absent).
STRUCTURES = ("lie_poisson", "log_canonical", "polynomial")

#: Largest safetensors header read to find a file's structure (the format's own limit).
_MAX_HEADER_BYTES = 100_000_000


def model_structure(path: str | os.PathLike[str]) -> str:
    """The ``structure`` a model file's metadata states (``lie_poisson`` where it states none),
    from the safetensors header alone. A file whose header cannot be read is reported as
    ``lie_poisson``, so that the loader names what is wrong with it; a readable header with an
    unknown structure raises one :class:`~poisson_rs.untrusted.InputError` (ValueError)."""
    try:
        # Non-blocking open and a regular-file check on the open descriptor: a FIFO or a device
        # is left to the loader, which refuses it by name (check_input_file), never read here.
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                return STRUCTURES[0]
            size = int.from_bytes(f.read(8), "little")
            if not 0 < size <= _MAX_HEADER_BYTES:
                return STRUCTURES[0]
            header = json.loads(f.read(size))
        meta = header.get("__metadata__") if isinstance(header, dict) else None
        value = meta.get("structure", STRUCTURES[0]) if isinstance(meta, dict) else STRUCTURES[0]
    except (OSError, ValueError, UnicodeDecodeError):
        return STRUCTURES[0]
    with parsing(f"model file {os.fspath(path)}", "structure"):
        if value not in STRUCTURES:
            text = value[:60] if isinstance(value, str) else repr(value)[:60]
            raise ValueError(f"unknown model structure {text!r}; known: {', '.join(STRUCTURES)}")
    return str(value)


_LOG_REQUIRED = ("format", "structure", "widths", "system", "h_max", "domain")


def parse_log_canonical_metadata(
    raw: Mapping[str, str], source: str = "model metadata"
) -> dict[str, Any]:
    """Checks and decodes the metadata of a log-canonical model file: ``system`` becomes a
    :class:`~poisson_rs.structures.log_canonical.LogCanonicalSystem`, ``h_max`` a positive
    float, ``domain`` a box ``{"kind": "box", "x_min": [...], "x_max": [...]}`` in the open
    positive orthant, ``widths`` a tuple. Any problem raises one
    :class:`~poisson_rs.untrusted.InputError` (ValueError) naming ``source`` and the field."""
    from .structures.log_canonical import LogCanonicalSystem

    with parsing(source):
        if not isinstance(raw, Mapping):
            raise TypeError(f"metadata must be a mapping of strings, got {type(raw).__name__}")
        missing = [k for k in _LOG_REQUIRED if k not in raw]
        if missing:
            raise ValueError(f"model metadata lacks {', '.join(missing)}")
    meta: dict[str, Any] = dict(raw)
    with parsing(source, "structure"):
        if raw["structure"] != "log_canonical":
            raise ValueError(f"structure is {raw['structure'][:40]!r}, not 'log_canonical'")
    with parsing(source, "system"):
        spec = _json(raw, "system")
        meta["system"] = LogCanonicalSystem.from_dict(spec)
    dim = meta["system"].dim
    with parsing(source, "h_max"):
        meta["h_max"] = _float(raw, "h_max")
        if not 0 < meta["h_max"] < math.inf:
            raise ValueError(f"metadata 'h_max' must be a finite number > 0, got {raw['h_max']!r}")
    _read_widths(source, raw, meta)
    _read_taylor_order(source, raw, meta)
    with parsing(source, "domain"):
        domain = _json(raw, "domain")
        ok = isinstance(domain, dict) and domain.get("kind") == "box"
        bounds: list[Any] = [domain.get(k) if ok else None for k in ("x_min", "x_max")]
        lo, hi = bounds
        ok = ok and all(
            isinstance(v, list)
            and len(v) == dim
            and all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in v)
            for v in (lo, hi)
        )
        if not ok or not all(0 < a < b < math.inf for a, b in zip(lo, hi, strict=True)):
            raise ValueError(
                f"metadata 'domain' must be a box with {dim} bounds 0 < x_min < x_max: "
                f"{raw['domain'][:80]!r}"
            )
        meta["domain"] = domain
    return meta
