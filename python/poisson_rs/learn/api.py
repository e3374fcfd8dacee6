"""``pr.learn``: a Poisson integrator from trajectories, with H learned or never formed."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ..export import model_bytes
from ..hamiltonian_library import library_families, supports_library
from ..integrators import LearnedIntegrator, TaylorIntegrator
from ..structures.lie_poisson import LieAlgebra, LiePoissonSystem
from ..taylor import system_taylor_terms
from .data import TrajectoryData, check_seed, prepare
from .data import refuse_drift as _refuse_drift
from .fixed_step import FixedStepIntegrator
from .mlp_hamiltonian import mlp_family
from .options import (
    EXACT_LEVEL,
    MAX_DEGREE,
    ORDER_RANGE,
    check_bool,
    check_int,
    check_map_options,
    check_seconds,
)
from .report import Candidate, LearnReport
from .scoring import all_records as _all_records
from .scoring import errors as _errors
from .scoring import progress_bar as _progress_bar

__all__ = ["MODES", "learn", "learning_on_found", "resolve_algebra"]

MODES = ("auto", "hamiltonian", "map", "hj+data")
#: Degrees of the map's polynomial S(h, ·) tried (the held-out one-step error chooses).
MAP_DEGREES = (4, 6)
#: What mode "hj+data" learns on top of the known H.
CORRECTIONS = ("polynomial", "network")
#: Polynomial degrees tried, smallest first.
AUTO_DEGREES = (2, 3, 4)
_ALGEBRAS = {"so3": LieAlgebra.so3, "se3": LieAlgebra.se3, "sl2": LieAlgebra.sl2}


def resolve_algebra(algebra: Any, system: Any) -> LieAlgebra:
    """The Lie algebra from ``algebra`` (a LieAlgebra or "so3"/"se3"/"sl2") or ``system``."""
    if system is not None:
        # Learning through the integrator runs on T*G: a system a learned S trains for.
        if not getattr(system, "trainable", False):
            raise TypeError(f"system must be a LiePoissonSystem, got {type(system).__name__}")
        if algebra is not None and resolve_algebra(algebra, None) != system.algebra:
            raise ValueError("algebra and system.algebra differ; give one of them")
        return system.algebra
    if isinstance(algebra, LieAlgebra):
        return algebra
    if isinstance(algebra, str) and algebra in _ALGEBRAS:
        return _ALGEBRAS[algebra]()
    if algebra is None:
        raise ValueError("learn needs the Poisson structure: give algebra= or system=")
    raise ValueError(f"algebra must be a LieAlgebra or one of {tuple(_ALGEBRAS)}, got {algebra!r}")


def _domain(data: TrajectoryData) -> dict[str, Any]:
    """A cube 10 % wider than the data: rollouts that leave it are counted and warned about."""
    half = float(np.max(np.maximum(np.abs(data.lo), np.abs(data.hi))))
    return {"kind": "cube", "half_width": 1.1 * half}


def _record(
    data: TrajectoryData,
    family: str,
    mode: str,
    seed: int,
    command: str | None,
    seconds: float,
    fixed_step: bool = False,
) -> dict[str, Any]:
    """The provenance a model file records; ``step_h`` (the one h a learned time-h map steps
    at) where ``fixed_step``."""
    extra = {"step_h": data.h} if fixed_step else {}
    return {
        **extra,
        "name": f"learned-{family}",
        "learn_mode": mode,
        "learn_family": family,
        "data_sha256": data.digest,
        "data_shape": list(data.shape),
        "data_h": data.h,
        "command": command or "poisson_rs.learn",
        "seed": seed,
        "train_seconds": round(seconds, 3),
    }


def _polynomial_candidate(
    data, algebra, degree, order, mode, seed, command, options, family=None, sparse=True
):
    from .hamiltonian import fit_polynomial  # torch is imported on first use only

    fit = fit_polynomial(
        data, algebra, degree, order=order, family=family, sparse=sparse, **options
    )
    powers, coeffs = system_taylor_terms(fit.system, fit.order, "exp")
    family = f"poly{degree}"
    raw = model_bytes(
        powers=powers,
        coeffs=coeffs,
        layers=[],
        mlp_power=1,
        chart="exp",
        system=fit.system,
        h_max=math.inf,
        domain=_domain(data),
        taylor_order=fit.order,
        record=_record(data, family, mode, seed, command, fit.seconds),
    )
    stepper = TaylorIntegrator(raw)
    one, roll = _errors(stepper, data)
    return Candidate(
        family=family,
        parameters=fit.n_parameters,
        order=fit.order,
        seconds=fit.seconds,
        one_step=one,
        rollout=roll,
        stepper=stepper,
        model_bytes=raw,
        system=fit.system,
    )


def _map_candidate(data, algebra, mode, seed, command, options):
    options = dict(options)
    kind = options.pop("kind", "polynomial")
    if kind == "polynomial":
        return _polynomial_map_candidate(data, algebra, mode, seed, command, options)
    return _network_map_candidate(data, algebra, mode, seed, command, options)


def _polynomial_map_candidate(data, algebra, mode, seed, command, options):
    from ..structures.lie_poisson import Polynomial
    from .map import fit_polynomial_map

    if "degree" not in options:
        # Degree by held-out one-step error: the larger S fits exact data to round-off, the
        # smaller one overfits noise less.
        tried = [
            _polynomial_map_candidate(data, algebra, mode, seed, command, {**options, "degree": d})
            for d in MAP_DEGREES
        ]
        best = min(tried, key=lambda c: c.one_step)
        best.seconds = sum(c.seconds for c in tried)
        return best
    t0 = time.perf_counter()
    s, basis, n_params = fit_polynomial_map(data, algebra, **options)
    seconds = time.perf_counter() - t0
    nz = s != 0.0
    powers = np.concatenate([np.full((basis.size, 1), 2, np.int64), basis.powers], axis=1)
    family = f"map-poly{basis.degree}"
    raw = model_bytes(
        # S(t, p) = (t/h)²·S(h, p): the map is learned at the data's h only, and with no t¹
        # term the file records no H (H is never formed).
        powers=powers[nz],
        coeffs=s[nz] / data.h**2,
        layers=[],
        mlp_power=1,
        chart="exp",
        system=LiePoissonSystem(algebra, Polynomial({(0,) * algebra.dim: 0.0}), name="learned-map"),
        h_max=data.h,
        domain=_domain(data),
        record=_record(data, family, mode, seed, command, seconds, fixed_step=True),
    )
    stepper = FixedStepIntegrator(raw)
    one, roll = _errors(stepper, data)
    return Candidate(
        family=family,
        parameters=n_params,
        order=0,
        seconds=seconds,
        one_step=one,
        rollout=roll,
        stepper=stepper,
        model_bytes=raw,
    )


def _network_candidate(
    s_fn: Any,
    system: LiePoissonSystem,
    family: str,
    parameters: int,
    order: int,
    seconds: float,
    data: TrajectoryData,
    mode: str,
    seed: int,
    command: str | None,
    fixed_step: bool = False,
) -> Candidate:
    """A learned generating function (Taylor terms + MLP, exp chart) as a model file recording
    ``system`` and its provenance, stepped in Rust and scored on the held-out data; with
    ``fixed_step`` (a map trained at the data's h only) it steps at that h alone."""
    raw = model_bytes(
        powers=s_fn.powers.numpy(),
        coeffs=s_fn.coeffs.detach().numpy(),
        layers=s_fn.exported_layers(),
        mlp_power=s_fn.mlp_power,
        mlp_inputs=s_fn.inputs,
        chart="exp",
        system=system,
        h_max=data.h,
        domain=_domain(data),
        taylor_order=order,
        record=_record(data, family, mode, seed, command, seconds, fixed_step=fixed_step),
    )
    stepper = (FixedStepIntegrator if fixed_step else LearnedIntegrator)(raw)
    one, roll = _errors(stepper, data)
    return Candidate(
        family=family,
        parameters=parameters,
        order=order,
        seconds=seconds,
        one_step=one,
        rollout=roll,
        stepper=stepper,
        model_bytes=raw,
        system=None,
    )


def _network_map_candidate(data, algebra, mode, seed, command, options):
    from .map import fit_map

    t0 = time.perf_counter()
    s_fn, n_params = fit_map(data, algebra, seed=seed, **options)
    seconds = time.perf_counter() - t0
    system = _map_base(s_fn, algebra)
    return _network_candidate(
        s_fn, system, "map", n_params, 0, seconds, data, mode, seed, command, fixed_step=True
    )


def _blend_candidate(data, known, order, lam, mode, seed, command, options):
    from .blend import fit_blended_map

    t0 = time.perf_counter()
    s_fn, _ = fit_blended_map(data, known, order=order or 3, lam=lam, seed=seed, **(options or {}))
    seconds = time.perf_counter() - t0
    return _network_candidate(
        s_fn, known, "known+network", s_fn.n_parameters(), order or 3, seconds, data, mode,
        seed, command,
    )  # fmt: skip


def _map_base(s_fn: Any, algebra: LieAlgebra) -> LiePoissonSystem:
    """The system a map's file records: H₀ of its t¹ terms −t·H₀ (model files check that the
    t¹ terms are −t·H of the recorded system); the map itself is the learned S, not H₀'s flow."""
    from ..structures.lie_poisson import Polynomial

    powers = s_fn.powers.numpy()
    coeffs = s_fn.coeffs.detach().numpy()
    terms = {
        tuple(int(v) for v in row[1:]): -float(c)
        for row, c in zip(powers, coeffs, strict=True)
        if row[0] == 1
    }
    return LiePoissonSystem(
        algebra, Polynomial(terms or {(0,) * algebra.dim: 0.0}), name="learned-map"
    )


def learning_on_found(
    trajectories: Any, h: float, **options: Any
) -> Callable[[Any, int], tuple[Any, LearnReport]]:
    """What structure discovery's step 5 calls (``given`` of
    :func:`~poisson_rs.learn.discover.learn_discover`): (found structure, degree d) → H alone,
    a polynomial of degree d, learned with that structure given
    (``learn(trajectories, h, structure=found, degree=d, mode="hamiltonian", **options)``), on
    the same records, split and options as the discovery."""

    def given(found: Any, degree: int) -> tuple[Any, LearnReport]:
        return learn(
            trajectories, h, mode="hamiltonian", structure=found, degree=degree, progress=False,
            **options,
        )  # fmt: skip

    return given


def learn(
    trajectories: Any,
    h: float,
    *,
    algebra: LieAlgebra | str | None = None,
    system: LiePoissonSystem | None = None,
    structure: Any = None,
    mode: str = "auto",
    degree: int | None = None,
    max_degree: int | None = None,
    order: int | None = None,
    test_fraction: float = 0.2,
    seed: int = 0,
    horizon: int = 4,
    max_iter: int = 30,
    map_options: dict[str, Any] | None = None,
    command: str | None = None,
    verbose: bool = False,
    refit: bool = True,
    correction: str = "polynomial",
    lam: float = 1.0,
    progress: bool | None = None,
    max_seconds: float | None = None,
) -> tuple[Any, LearnReport]:
    """Learns a Poisson integrator from trajectories whose Poisson structure is known.

    Parameters
    ----------
    trajectories : array (n_traj, n_records, dim), one (n_records, dim) array, a list of such
        arrays (lengths may differ), a torch tensor, or a path (.npz, .csv, Zarr from
        ``ensembles.to_zarr``; see :func:`poisson_rs.learn.data.load_trajectories` for the
        checks on files). Records are ``h`` apart in time.
    h : float
        The record spacing (time units), in :data:`poisson_rs.learn.data.H_RANGE`.
    algebra, system : the Lie algebra (a LieAlgebra or "so3", "se3", "sl2"), or a system whose
        algebra it is (its Hamiltonian is used by mode "hj+data" only, as the known part). One
        of them (or ``structure``) is required: nothing is assumed.
    structure : ``"discover"`` to learn the bracket as well (:mod:`poisson_rs.learn.discover`:
        the bivector families every structure offers, smallest first, the smallest that
        reaches the data's noise level kept, a found Lie algebra's H fitted again on T*G with
        noisy records; modes "auto" and "hamiltonian"), or the Poisson
        structure, as any system on it (:class:`poisson_rs.PoissonSystem`;
        its own H is ignored) or a Lie algebra: a Lie–Poisson system or algebra learns as
        ``system=``/``algebra=`` do; any other structure (affine, polynomial bivector, charged
        particle, ...) learns H from the family it offers
        (:meth:`~poisson_rs.protocols.PoissonSystemBase.hamiltonian_family`) through its own
        Taylor-HJ integrator (:mod:`poisson_rs.learn.structure_fit`), then, where no degree
        explains the data, the term libraries (:mod:`poisson_rs.hamiltonian_library`) and last
        a cubic polynomial plus a tanh network fitted through the implicit midpoint rule
        (:mod:`poisson_rs.learn.mlp_hamiltonian`; fitted on the training records only), in the
        modes it lists in ``learn_modes()``; another mode is refused, naming the mode and the
        structure. There
        the fit is on one-step residuals (``horizon``, shooting and ``map_options`` are the
        T*G path's).
    mode : "auto" (smallest model that explains the data: polynomial H of degree 2, 3, 4, then
        a map), "hamiltonian" (polynomial H of ``degree``, or the degrees in turn), "map" (the
        time-h map's generating function, H never formed; it steps at the data's h only),
        "hj+data" (``system``'s H is known or its known part; a correction is learned, see
        :mod:`poisson_rs.learn.blend`).
    degree, order : polynomial degree of H (1..4) and Taylor-HJ order K (1..12; default:
        chosen, see :func:`poisson_rs.learn.hamiltonian.default_order`).
    max_degree : the largest degree modes "auto" and "hamiltonian" try (1..4; default 4): each
        degree costs more than the one before.
    test_fraction, seed : held-out share of the trajectories (of the records when there is only
        one) and the seed (an integer >= 0) that picks them. Where nothing can be held out (two
        trajectories, one of a few records), the report says the errors are training errors.
    horizon, max_iter : longest multi-step residual (1..64) and Levenberg–Marquardt iterations
        (1..10000).
    map_options : the map's family and options: ``kind`` "polynomial" (default: S(h, ·) a
        polynomial in p, :func:`poisson_rs.learn.map.fit_polynomial_map`, e.g. ``degree``) or
        "network" (:func:`poisson_rs.learn.map.fit_map`); for mode "hj+data" with
        ``correction="network"``, options of :func:`poisson_rs.learn.blend.fit_blended_map`.
        Unknown keys are refused.
    command : recorded in the model file.
    correction, lam : mode "hj+data": "polynomial" (H = known + a polynomial of ``degree``;
        default the known H's degree, at least 2; the known H's degree must be <= 4) or
        "network" (S = the known H's Taylor series of ``order`` (default 3) + t^(K+1)·MLP,
        ``map_options`` for :func:`poisson_rs.learn.blend.fit_blended_map`), and λ of
        loss_HJ + λ·loss_data.
    refit : after the choice on held-out data, refit the kept polynomial's coefficients on every
        record (its one-step and rollout errors in the report stay the held-out ones); in
        structure discovery, H's coefficients on the kept bracket, once a pair explains the
        data.
    progress : a progress bar with an ETA over the fits on stderr (tqdm); default: when stderr
        is a terminal.
    max_seconds : ``structure="discover"`` only: a time budget (s). Once it is spent no further
        (bracket, H) pair is started (the first always is); the pair running finishes, the rest
        are listed as not tried, and the best tried is kept (marked NOT EXPLAINED where none
        reached the noise level). Default: none.

    Returns
    -------
    (stepper, report): ``stepper`` integrates with :func:`poisson_rs.integrate` (a Taylor-HJ
    integrator of the learned H, any h; or a learned map, a
    :class:`~poisson_rs.learn.fixed_step.FixedStepIntegrator` that refuses any h but the
    data's); ``report`` a :class:`~poisson_rs.learn.report.LearnReport` (``print(report)``
    shows every candidate).

    Raises ValueError naming the argument for a bad option and naming the input and field for
    bad data (see :func:`poisson_rs.learn.data.prepare`), all before any fit; refuses data whose
    Casimirs drift far beyond what their noise explains (not from a Lie–Poisson system of this
    algebra) and warns where they drift beyond it at all.
    """
    # Every option is checked here, before any work.
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    max_seconds = check_seconds(max_seconds, "max_seconds")
    if max_seconds is not None and not (isinstance(structure, str) and structure == "discover"):
        raise ValueError("max_seconds applies to structure='discover' only")
    if structure is not None:
        if algebra is not None or system is not None:
            raise ValueError("structure: give the structure alone, not with algebra= or system=")
        if isinstance(structure, str) and structure == "discover":
            from .discover import learn_discover

            given = learning_on_found(
                trajectories, h, order=order, test_fraction=test_fraction, seed=seed,
                max_iter=max_iter, refit=refit,
            )  # fmt: skip
            return learn_discover(
                trajectories, h, mode=mode, degree=degree, max_degree=max_degree, order=order,
                test_fraction=test_fraction, seed=seed, max_iter=max_iter, verbose=verbose,
                progress=progress, refit=refit, given=given, max_seconds=max_seconds,
            )  # fmt: skip
        if getattr(structure, "trainable", False):
            system = structure  # a Lie–Poisson system: learning runs on T*G
        elif hasattr(structure, "learn_modes"):
            return _learn_on_structure(
                trajectories, h, structure, mode=mode, degree=degree, max_degree=max_degree,
                order=order, test_fraction=test_fraction, seed=seed, max_iter=max_iter,
                verbose=verbose, refit=refit, progress=progress,
            )  # fmt: skip
        elif isinstance(structure, (str, LieAlgebra)):
            algebra = structure
        else:
            raise TypeError(
                "structure must be a Poisson system (poisson_rs.PoissonSystem; its H is "
                f"ignored) or a Lie algebra, got {type(structure).__name__}"
            )
    if mode == "hj+data":
        if system is None:
            raise ValueError(
                "mode 'hj+data' needs the known part of H: give system= (a LiePoissonSystem)"
            )
        if correction not in CORRECTIONS:
            raise ValueError(f"correction must be one of {CORRECTIONS}, got {correction!r}")
        if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not 0 <= lam < math.inf:
            raise ValueError(f"lam must be a finite number >= 0, got {lam!r}")
    if degree is not None:
        degree = check_int(degree, "degree", 1, MAX_DEGREE)
    if max_degree is not None:
        max_degree = check_int(max_degree, "max_degree", 1, MAX_DEGREE)
        if degree is not None and degree > max_degree:
            raise ValueError(f"degree = {degree} exceeds max_degree = {max_degree}")
    if order is not None:
        order = check_int(order, "order", *ORDER_RANGE)
    horizon = check_int(horizon, "horizon", 1, 64)
    max_iter = check_int(max_iter, "max_iter", 1, 10_000)
    seed = check_seed(seed)
    verbose = check_bool(verbose, "verbose")
    refit = check_bool(refit, "refit")
    if progress is not None:
        progress = check_bool(progress, "progress")
    if command is not None and not isinstance(command, str):
        raise ValueError(f"command must be a string, got {type(command).__name__}")
    blend = mode == "hj+data" and correction == "network"
    map_options = check_map_options(map_options, "blend" if blend else "map")
    alg = resolve_algebra(algebra, system)
    known_degree = 0
    if mode == "hj+data" and not blend:
        assert system is not None
        known_degree = max(
            (sum(e) for e, c in system.polynomial.terms.items() if c != 0.0), default=0
        )
        if known_degree > MAX_DEGREE:
            raise ValueError(
                f"system: the known H has degree {known_degree}; mode 'hj+data' with the "
                f"polynomial correction fits H = known + correction through its Taylor-HJ "
                f"series, formed for degrees up to {MAX_DEGREE} (give correction='network', "
                "or a known part of lower degree)"
            )
    data = prepare(trajectories, h, alg, test_fraction=test_fraction, seed=seed)
    _refuse_drift(data)
    n = alg.dim
    threshold = 1.5 * math.sqrt(2 * n) * data.noise + 1e-12
    options = {"horizon": horizon, "max_iter": max_iter, "verbose": verbose}
    held = bool(data.test)
    # The words the report uses: with nothing held out the errors are training errors.
    err = "held-out one-step error" if held else "training one-step error (nothing held out)"
    candidates: list[Candidate] = []
    kept: Candidate | None = None
    explained = True  # False where no candidate reaches the noise level
    top = max_degree or MAX_DEGREE
    degrees = [degree] if degree is not None else [d for d in AUTO_DEGREES if d <= top] or [top]
    planned = {
        "auto": len(degrees) + 1 + int(refit and held),
        "hamiltonian": len(degrees) + int(refit and held),
        "map": 1,
        "hj+data": 1,
    }[mode]
    bar = _progress_bar(planned, progress)
    try:
        if blend:
            bar.set_postfix_str("known+network")
            kept = _blend_candidate(data, system, order, lam, mode, seed, command, map_options)
            kept.reason = "the known H's series plus a network trained on loss_HJ + λ·loss_data"
            candidates.append(kept)
            bar.update(1)
        elif mode == "hj+data":
            assert system is not None
            d = degree or max(2, known_degree)
            bar.set_postfix_str(f"known+poly{d}")
            kept = _polynomial_candidate(
                data, alg, d, order, mode, seed, command, {**options, "known": system.polynomial}
            )
            kept.family = f"known+poly{d}"
            kept.reason = "the known H plus a polynomial correction fitted to the data"
            candidates.append(kept)
            bar.update(1)
        if mode in ("auto", "hamiltonian"):
            for d in degrees:
                bar.set_postfix_str(f"poly{d}")
                cand = _polynomial_candidate(data, alg, d, order, mode, seed, command, options)
                candidates.append(cand)
                bar.update(1)
                if verbose:
                    print(f"poly{d}: one-step {cand.one_step:.3e}, {cand.seconds:.1f} s")
                if math.isfinite(threshold) and cand.one_step <= threshold:
                    kept = cand
                    cand.reason = f"the smallest family whose {err} reaches the data's noise level"
                    break
                if not math.isfinite(threshold) and cand.one_step <= EXACT_LEVEL:
                    kept = cand
                    cand.reason = f"noise level unknown; {err} below {EXACT_LEVEL:g} (exact data)"
                    break
                cand.reason = (
                    f"{err} {cand.one_step:.2e} above the noise level {threshold:.2e}"
                    if math.isfinite(threshold)
                    else "noise level unknown"
                )
        if kept is None and mode in ("auto", "map"):
            bar.set_postfix_str("map")
            cand = _map_candidate(data, alg, mode, seed, command, map_options)
            candidates.append(cand)
            bar.update(1)
            cand.reason = (
                f"its {err} reaches the data's noise level"
                if cand.one_step <= threshold
                else f"{err} {cand.one_step:.2e}"
            )
            if mode == "map" or cand.one_step <= threshold:
                kept = cand
        if kept is None:
            best = min(c.one_step for c in candidates)
            if not math.isfinite(threshold):
                # Noise unknown (too few records per trajectory): the smallest candidate within
                # 2× of the best error.
                kept = next(c for c in candidates if c.one_step <= 2.0 * best)
                kept.reason = f"the smallest family within 2× of the best {err}"
            else:
                kept = next(c for c in candidates if c.one_step == best)
                kept.reason = f"no family reached the noise level; the best {err}"
                explained = False
        if refit and mode != "hj+data" and kept.system is not None and held:
            # The family is chosen on held-out data; its coefficients are then fitted on every
            # record (with one trajectory, the held-out end is the longest lever on the phase).
            terms = [e for e, c in kept.system.polynomial.terms.items() if c != 0.0]
            if terms:
                bar.set_postfix_str(f"{kept.family} on all records")
                whole = _all_records(data)
                final = _polynomial_candidate(
                    whole,
                    alg,
                    max(map(sum, terms)),
                    kept.order,
                    mode,
                    seed,
                    command,
                    options,
                    family=terms,
                    sparse=False,
                )
                bar.update(1)
                final.one_step, final.rollout = kept.one_step, kept.rollout
                final.seconds += kept.seconds
                final.reason = kept.reason + "; coefficients refitted on all records"
                candidates[candidates.index(kept)] = final
                kept = final
        bar.total = bar.n  # the fits not needed (a family reached the noise level) are done
        bar.refresh()
    finally:
        bar.close()
    kept.kept = True
    for c in candidates:
        if c is not kept and c.reason.startswith("the smallest"):
            c.reason = "a smaller family was kept"
    report = LearnReport.of(
        data, mode=mode, candidates=candidates, kept=kept, threshold=threshold, seed=seed,
        explained=explained,
    )  # fmt: skip
    return kept.stepper, report


def _library_applies(library: Any, data: Any, verbose: bool) -> bool:
    """Whether ``library``'s terms are defined on every record: a library singular on some
    (a point at the origin under |z|^p, two points together under log-distances) is passed
    over by the search, which goes on to the next family; asked for by name it refuses the
    records (:func:`~poisson_rs.learn.structure_fit.fit_structure_hamiltonian`)."""
    try:
        library.check_states(np.concatenate(data.train + data.test), "trajectories")
    except ValueError as err:
        if verbose:
            print(f"{library.name}: passed over: {err}")
        return False
    return True


def _learn_on_structure(
    trajectories: Any,
    h: float,
    structure: Any,
    *,
    mode: str,
    degree: int | None,
    max_degree: int | None,
    order: int | None,
    test_fraction: float,
    seed: int,
    max_iter: int,
    verbose: bool,
    refit: bool,
    progress: bool | None,
) -> tuple[Any, LearnReport]:
    """:func:`learn` on a structure that offers its own Hamiltonian family: H of the degrees
    the structure lists in turn (or ``degree``) fitted through the structure's Taylor-HJ
    integrator, the smallest whose held-out one-step error reaches the data's noise level kept,
    then refitted on every record. Nothing here names a structure: what differs is asked of
    ``structure``."""
    from .structure_fit import fit_structure_hamiltonian

    modes = tuple(structure.learn_modes())
    title = getattr(structure, "title", type(structure).__name__)
    if mode not in modes:
        why = (
            f"the modes that apply to it: {', '.join(repr(m) for m in modes)}"
            if modes
            else "no mode of pr.learn applies to it (it offers no Hamiltonian family)"
        )
        raise ValueError(f"mode {mode!r} does not apply to the structure {title}; {why}")
    if degree is not None:
        degree = check_int(degree, "degree", 1, MAX_DEGREE)
    if max_degree is not None:
        max_degree = check_int(max_degree, "max_degree", 1, MAX_DEGREE)
        if degree is not None and degree > max_degree:
            raise ValueError(f"degree = {degree} exceeds max_degree = {max_degree}")
    if order is not None:
        order = check_int(order, "order", *ORDER_RANGE)
        if order not in structure.learn_orders():
            raise ValueError(
                f"order = {order} is not available on the structure {title}: its Taylor-HJ "
                f"orders are {', '.join(map(str, structure.learn_orders()))}"
            )
    max_iter = check_int(max_iter, "max_iter", 1, 10_000)
    seed = check_seed(seed)
    verbose = check_bool(verbose, "verbose")
    refit = check_bool(refit, "refit")
    if progress is not None:
        progress = check_bool(progress, "progress")
    data = prepare(trajectories, h, None, test_fraction=test_fraction, seed=seed, system=structure)
    _refuse_drift(data)
    threshold = 1.5 * math.sqrt(2 * data.dim) * data.noise + 1e-12
    held = bool(data.test)
    err = "held-out one-step error" if held else "training one-step error (nothing held out)"
    top = max_degree or MAX_DEGREE
    tried = structure.learn_degrees()
    degrees = [degree] if degree is not None else [d for d in tried if d <= top] or [top]

    def candidate(fit: Any) -> Candidate:
        one, roll = _errors(fit.stepper, data)
        return Candidate(
            family=fit.family.name,
            parameters=fit.n_parameters,
            order=fit.family.order,
            seconds=fit.seconds,
            one_step=one,
            rollout=roll,
            stepper=fit.stepper,
            system=fit.system,
            hamiltonian_family=fit.family.description,
            hamiltonian_text=fit.family.text(fit.theta),
            gauge=fit.family.gauge,
            fit=fit,
        )

    # Beyond polynomials: where no polynomial degree explains the data, the term libraries
    # (polynomials plus sin/cos of each coordinate, then, in even dimensions, plus the
    # log-distances of planar points, then plus their inverse distances; stepped by jets) on
    # structures with a jet realization, then a polynomial plus a network (midpoint rule).
    # They come last, so that data a smaller family explains never pay for them.
    plans: list[tuple[int, Any]] = [(d, None) for d in degrees]
    if degree is None:
        plans += [
            (lib.degree, lib)
            for lib in library_families(structure, order, top)
            if _library_applies(lib, data, verbose)
        ]
        # Last, where no term library is enough: an MLP H through the midpoint rule (a family
        # that fits itself).
        mlp = mlp_family(structure, top, seed=seed) if supports_library(structure) else None
        if mlp is not None:
            plans.append((mlp.degree, mlp))
    candidates: list[Candidate] = []
    kept: Candidate | None = None
    explained = True  # False where no candidate reaches the noise level
    bar = _progress_bar(len(plans) + int(refit and held), progress)
    try:
        for d, library in plans:
            bar.set_postfix_str(library.name if library is not None else f"poly{d}")
            fits_itself = getattr(library, "fit", None)
            if fits_itself is not None:
                fit = fits_itself(data, verbose=verbose)
            else:
                fit = fit_structure_hamiltonian(
                    data, structure, d, order=order, max_iter=max_iter, verbose=verbose,
                    family=library,
                )  # fmt: skip
            cand = candidate(fit)
            candidates.append(cand)
            bar.update(1)
            if verbose:
                print(f"{cand.family}: one-step {cand.one_step:.3e}, {cand.seconds:.1f} s")
            if math.isfinite(threshold) and cand.one_step <= threshold:
                kept = cand
                cand.reason = f"the smallest family whose {err} reaches the data's noise level"
                break
            if not math.isfinite(threshold) and cand.one_step <= EXACT_LEVEL:
                kept = cand
                cand.reason = f"noise level unknown; {err} below {EXACT_LEVEL:g} (exact data)"
                break
            cand.reason = (
                f"{err} {cand.one_step:.2e} above the noise level {threshold:.2e}"
                if math.isfinite(threshold)
                else "noise level unknown"
            )
        if kept is None:
            best = min(c.one_step for c in candidates)
            if not math.isfinite(threshold):
                kept = next(c for c in candidates if c.one_step <= 2.0 * best)
                kept.reason = f"the smallest family within 2× of the best {err}"
            else:
                kept = next(c for c in candidates if c.one_step == best)
                kept.reason = f"no family reached the noise level; the best {err}"
                explained = False
        if refit and held and not getattr(kept.fit.family, "linear", True):
            kept.reason += "; a network is fitted on the training records only (no refit)"
        elif refit and held:
            # The family is chosen on held-out data; its coefficients are then fitted on every
            # record.
            family = kept.fit.family
            terms = [e for e, t in zip(family.exponents, kept.fit.theta, strict=True) if t != 0]
            if terms:
                bar.set_postfix_str(f"{kept.family} on all records")
                fit = fit_structure_hamiltonian(
                    _all_records(data),
                    structure,
                    family.degree,
                    family=family.restrict(terms),
                    max_iter=max_iter,
                    sparse=False,
                    verbose=verbose,
                )
                bar.update(1)
                final = candidate(fit)
                final.one_step, final.rollout = kept.one_step, kept.rollout
                final.seconds += kept.seconds
                final.reason = kept.reason + "; coefficients refitted on all records"
                candidates[candidates.index(kept)] = final
                kept = final
        bar.total = bar.n
        bar.refresh()
    finally:
        bar.close()
    kept.kept = True
    for c in candidates:
        if c is not kept and c.reason.startswith("the smallest"):
            c.reason = "a smaller family was kept"
    report = LearnReport.of(
        data, mode=mode, candidates=candidates, kept=kept, threshold=threshold, seed=seed,
        explained=explained,
    )  # fmt: skip
    return kept.stepper, report
