"""Every stepper that existed before the structure protocol gives the same bits through it: the
digests below were taken from the build before the reorganisation (the same Rust core, the
Python layer of commit 01530b5), with the same calls (the family names kept as aliases); all 28
held through the reorganisation. Then the Lie–Poisson bisection step changed on purpose: its new
state is g(x)·μ, not sou from Newton's last iterate, so that the Casimirs no longer drift with
Newton's residual; the 7 rollouts that take that step changed in their last bits, and
:data:`AFTER_THE_CASIMIR_FIX` holds them. Then Newton on the generic Lie-groupoid path started
from a predicted p₀ (and se(3)'s chart and coadjoint action took closed forms): the 3 rollouts
that take that path (the learned rigid body, the heavy top's Taylor step, the affine system's on
its central extension) converge to the same steps to Newton's tolerance from another start, and
:data:`AFTER_THE_PREDICTOR` holds them. Then the implicit midpoint rule started the rigid body
and the heavy top from fixed-point sweeps after the Euler midpoint (and solved the heavy top's
Newton systems on their blocks): the same steps to Newton's tolerance in fewer updates, held in
:data:`AFTER_THE_MIDPOINT_SWEEPS`. Then the heavy top's Taylor step solved its Newton systems in
SIMD lanes (the Jacobian in forward mode and a pivoted Gauss–Jordan inverse instead of dual
numbers and nalgebra's LU; ``rust/tests/se3_lanes.rs`` checks its steps against the generic
one's to 1e-12): :data:`AFTER_THE_SE3_LANES`. Then the learned rigid body's network moved into
the so(3) lane Newton solve (forward-mode jets and reverse-mode gradients in lanes with the
portable tanh, instead of the batched kernel's fused tanh; ``rust/tests/network_lanes.rs`` checks
its steps against the generic one's to 1e-12): :data:`AFTER_THE_NETWORK_LANES`. Then the
log-canonical Taylor step started Newton from the predicted q_k − ½c∇S(q_k) and took ∇S at the
solution from its last update to first order (the same 200-step rollouts to 1.2e-14):
:data:`AFTER_THE_LOG_PREDICTOR`. Then the so(3) and se(3) lane solves did the same with ∇S at
the solution (x + Hess S·δ from the last update, not one more gradient pass; the same rollouts to
8e-15 after 200 steps on the rigid body, 7.5e-14 on the heavy top):
:data:`AFTER_THE_FIRST_ORDER_GRADIENT`. Then Lotka–Volterra's midpoint rule in x went into SIMD
lanes (Newton for the midpoint m with a closed-form lane Jacobian instead of for z = 2m − x
with dual numbers and nalgebra's LU; the same rollout to 1.7e-14 after 200 steps):
:data:`AFTER_THE_LOG_MIDPOINT_LANES`. Then Newton in the Cayley chart started from 2μ − tar(x₀, μ)
(tar's quadratic term included: 3.66 → 3.00 updates a step; the exponential chart's rollouts
keep their bits), the same rollouts to 1.3e-14 after 200 steps:
:data:`AFTER_THE_CAYLEY_PREDICTOR`. Then the se(3) lane solve took one fixed-point step with S's
t¹ terms at that start (a second-order start: 3.67 → 3.00 updates on the heavy top), the same
rollout to 2.2e-15 after 100 steps: :data:`AFTER_THE_SECOND_ORDER_START`. Then the order-n
realization's Taylor step went into SIMD lanes (∇S, ∇²S and ∂α from derivative polynomials in f64
instead of dual numbers; ``rust/tests/polynomial.rs`` checks its steps against the dual-number
step's to 1e-12 with the same Newton counts), the same rollout to 1.4e-17 after 50 steps:
:data:`AFTER_THE_POLYNOMIAL_LANES`. The learned models' network Hessian from tangents and one
adjoint left every digest here as it was. Then the exponential chart of every other Lie algebra
(the affine system's central extension among them) went into SIMD lanes by its Bernoulli series
(``rust/tests/series_lanes.rs`` checks its steps against the generic dual-number step's to 1e-12
with the same Newton counts from the same start), the same rollout to 6.1e-16 after 100 steps:
:data:`AFTER_THE_SERIES_LANES`. Then the so(3) lane solve in the exponential chart started from
a second-order p₀ (one fixed-point step with ∇S linearized at μ from the same pass's Hessian:
2.97 → 2.00 updates a step), the same rollouts to 4.4e-15 after 200 steps:
:data:`AFTER_THE_EXP_SECOND_ORDER_START`. Then the Cayley chart's start went second order the
same way (with S's t³ terms in the pass: 2.98 → 2.06 updates a step), and every other algebra's
exponential chart took its fixed-point step from μ's Hessian instead of a second pass; the
rollouts that take them moved by at most 8.2e-15: :data:`AFTER_THE_HESSIAN_STARTS`. The
learned models with plain inputs (the heavy top's, Lotka–Volterra's) and the rigid body's
large-step model joined the list then (:data:`LEARNED_MODELS`), before the network Hessian's
sums moved into registers, which kept every bit. Then the lane networks fused their
multiply-adds (and took the fused tanh), so the learned rollouts whose network term reaches the
last bits moved, by at most 1.8e-14 (the rigid body's large-step model, 100 steps of h = 0.5):
:data:`AFTER_THE_FUSED_NETWORK`. Then the rigid body's field took the factored form
(1/I_k − 1/I_j) μ_j μ_k (6 multiplications where μ × (μ/I) took 9 and 3 subtractions), so its
RK4 and midpoint rollouts moved, by at most 5.1e-15 after 200 steps:
:data:`AFTER_THE_FACTORED_FIELD`. Then the learned log-canonical step started Newton from its
Taylor terms alone and kept its network term's Hessian from the first update (the same 3.00
updates a step), so the Lotka–Volterra model's rollout moved, by at most 5.8e-15 after 200 steps:
:data:`AFTER_THE_NETWORK_START`. Then the se(3) lane solve took its chart's p-Jacobian from
closed 3×3 blocks of ∂tar/∂p and ∂tar/∂x instead of six forward-mode tangents (the same Jacobian
to rounding; ``rust/tests/se3_lanes.rs`` checks it against dual numbers to 1e-13): the heavy
top's Taylor rollout kept its bits, and the learned heavy top's (h = 0.5) moved by at most
1.05e-14 after 40 steps: :data:`AFTER_THE_SE3_JACOBIAN`. Nothing else may change."""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

import poisson_rs as pr
from poisson_rs.structures.polynomial import RealizationTaylorIntegrator, VectorFieldIntegrator

#: sha256 (first 16 hex digits) of each rollout's float64 bytes, before the change.
BEFORE = {
    "rb-taylor3-cayley": "5d5bb6f6a3b3a00f",
    "rb-taylor3-exp": "a29ca8f8c203e93c",
    "rb-taylor5-cayley": "ca71e3d81f5f5094",
    "rb-taylor5-exp": "d966ecb4eaa9d0fd",
    "rb-rk4": "4f1988946c7440c1",
    "rb-midpoint": "85317747b51ee9e1",
    "rb-splitting": "fb7d1885aba8a994",
    "rb-splitting4": "7f31114f1e5c45db",
    "rb-dmv": "e1df8a8dab03252a",
    "rb-splitting_casimir": "eec05319bd815f70",
    "rb-learned-default": "99f730b595d440cd",
    "top-taylor3-exp": "296723c4e6c4760f",
    "top-rk4": "2babaaae0bc09877",
    "top-midpoint": "59d54dac902703cd",
    "top-splitting": "82ba08db7ed6e3bf",
    "lv-taylor1": "13613b054dea61e6",
    "lv-taylor3": "d156ad875b3da116",
    "lv-taylor5": "6ee88eda8b073e19",
    "lv-rk4": "da02e9ebe00c0cea",
    "lv-midpoint": "f2fbe860ae9d9e5f",
    "lv-log_splitting": "3fa624fe084b49a3",
    "lv-log_splitting4": "8897316accc04116",
    "affine-taylor3": "d06caf9f56ccf672",
    "affine-rk4": "3440723dcc42411a",
    "affine-midpoint": "7a96fefe3cbfc166",
    "nambu-taylor3": "fbb37b386197a536",
    "nambu-rk4": "6006a63f0f2dc3af",
    "nambu-midpoint": "dc832386d643d406",
}


#: The Lie–Poisson bisection rollouts (the rigid body's Taylor and learned steps, the heavy
#: top's, the affine system's on its central extension) after the Casimir fix.
AFTER_THE_CASIMIR_FIX = {
    "rb-taylor3-cayley": "d3256ce245bf2718",
    "rb-taylor3-exp": "edb4ff2d966ecaa0",
    "rb-taylor5-cayley": "1b88253d1ddf3829",
    "rb-taylor5-exp": "562430ad2b395389",
    "rb-learned-default": "8596b247ba6408de",
    "top-taylor3-exp": "1f0e04a117687026",
    "affine-taylor3": "52e27fa125676983",
}


#: The generic Lie-groupoid bisection rollouts after the predicted start and se(3)'s closed forms.
AFTER_THE_PREDICTOR = {
    "rb-learned-default": "b3797f6995ac7ad7",
    "top-taylor3-exp": "1754be7f7802ce74",
    "affine-taylor3": "0560a72164a06bd1",
}


#: The rigid body's and the heavy top's midpoint rollouts after the sweeps and the block solve.
AFTER_THE_MIDPOINT_SWEEPS = {
    "rb-midpoint": "ee3e773d68bad3d7",
    "top-midpoint": "237a66a55f7d632e",
}


#: The heavy top's Taylor rollout after its Newton solve moved into SIMD lanes.
AFTER_THE_SE3_LANES = {
    "top-taylor3-exp": "84eb39ed6c76c492",
}


#: The learned rigid body's rollout after its network moved into the lane Newton solve.
AFTER_THE_NETWORK_LANES = {
    "rb-learned-default": "2dc4dc64cee9b497",
}


#: The log-canonical Taylor rollouts after the predicted start and the first-order ∇S at the
#: solution.
AFTER_THE_LOG_PREDICTOR = {
    "lv-taylor1": "2ec7bff426a1385c",
    "lv-taylor3": "df66f887c689c0d9",
    "lv-taylor5": "81e30a4b5210a299",
}


#: The so(3) and se(3) lane-solved rollouts after ∇S at the solution went first order.
AFTER_THE_FIRST_ORDER_GRADIENT = {
    "rb-learned-default": "2daf017c220d2b7e",
    "rb-taylor3-cayley": "1d3a6b6b3a57a35d",
    "rb-taylor3-exp": "26ee9be812d718dd",
    "rb-taylor5-cayley": "dd729b684c25a71b",
    "rb-taylor5-exp": "df398bbdc9c99696",
    "top-taylor3-exp": "5f569d1446b3ee2a",
}


#: Lotka–Volterra's midpoint rollout after its step went into lanes.
AFTER_THE_LOG_MIDPOINT_LANES = {
    "lv-midpoint": "1bd2d1d73af827ef",
}


#: The rigid body's Cayley-chart rollouts (Taylor-HJ and the learned default model) after
#: Newton's start took the chart's quadratic term.
AFTER_THE_CAYLEY_PREDICTOR = {
    "rb-learned-default": "b34e5a0cc94fe468",
    "rb-taylor3-cayley": "e00e5025eb3ffdc4",
    "rb-taylor5-cayley": "d4c5f8e1994059de",
}


#: The heavy top's lane-solved rollout after Newton's start on se(3) went second order.
AFTER_THE_SECOND_ORDER_START = {
    "top-taylor3-exp": "e5f6e2863ae6337d",
}


#: The order-n realization's Taylor rollout after its Newton solve went into lanes.
AFTER_THE_POLYNOMIAL_LANES = {
    "nambu-taylor3": "472e02a997bab72d",
}


#: The affine system's Taylor rollout after the series chart's Newton solve went into lanes.
AFTER_THE_SERIES_LANES = {
    "affine-taylor3": "840d43696d386876",
}


#: The rigid body's exponential-chart Taylor rollouts after Newton's start there went second
#: order.
AFTER_THE_EXP_SECOND_ORDER_START = {
    "rb-taylor3-exp": "c9f3b647821ab21c",
    "rb-taylor5-exp": "5b75878987e32bb0",
}


#: The rollouts of the so(3) Cayley chart (Taylor-HJ and the learned default model) and of the
#: other exponential charts (the heavy top's, the affine system's central extension) after
#: their Newton starts took μ's Hessian.
AFTER_THE_HESSIAN_STARTS = {
    "rb-learned-default": "2409105a79a3476d",
    "rb-taylor3-cayley": "45fed050abac2c18",
    "rb-taylor5-cayley": "162d48e51f82c253",
    "top-taylor3-exp": "7fac84595c151f2d",
    "affine-taylor3": "4dfbc34280da07ef",
}


#: The learned models with plain inputs (t, p) and the rigid body's large-step model, first
#: recorded with the build whose network Hessian summed each entry unit by unit in memory
#: (848f834); the later changes keep their bits.
LEARNED_MODELS = {
    "rb-learned-large-step": "1fc2cc237379efb2",
    "top-learned-h05": "cf187dd0001c0186",
    "lv-learned-h01": "95fd4ce575fe0dc9",
}


#: The learned rollouts after the lane networks fused their multiply-adds (the Lotka–Volterra
#: model's t⁵-scaled term rounds away against its Taylor terms and keeps its bits).
AFTER_THE_FUSED_NETWORK = {
    "rb-learned-default": "804fd079284b7701",
    "rb-learned-large-step": "b8848f78b9baebd4",
    "top-learned-h05": "d76d8cf984991e9d",
}


def _digests() -> dict[str, str]:
    out: dict[str, str] = {}

    def dig(name: str, stepper: Any, x0: np.ndarray, h: float, n: int) -> None:
        traj = pr.integrate(stepper, x0, h, n)
        out[name] = hashlib.sha256(np.ascontiguousarray(traj).tobytes()).hexdigest()[:16]

    rb = pr.RigidBody()
    x_rb = np.array([[1.0, 1.0, 2.0], [3.0, 2.0, 0.0]])
    for k in (3, 5):
        for chart in ("cayley", "exp"):
            dig(f"rb-taylor{k}-{chart}", pr.taylor_integrator(rb, k, chart), x_rb, 0.1, 200)
    for m in pr.classical_methods(rb):
        if m != "dop853":
            dig(f"rb-{m}", pr.classical(rb, m), x_rb, 0.1, 200)
    dig("rb-learned-default", pr.load_model(), x_rb, 0.1, 200)
    dig("rb-learned-large-step", pr.load_model("large_step_h05"), x_rb, 0.5, 100)
    top = pr.HeavyTop()
    x_top = np.array([[0.3, -0.8, 1.2, 0.6, 0.0, 0.8], [2.0, 0.5, -1.0, 0.0, 0.6, 0.8]])
    dig("top-taylor3-exp", pr.taylor_integrator(top, 3), x_top, 0.1, 100)
    x_in = np.array([[0.3, -0.8, 1.2, 0.6, 0.0, 0.8], [0.5, 0.2, -0.4, 0.0, 0.6, 0.8]])
    dig("top-learned-h05", pr.load_model("heavy_top_h05"), x_in, 0.5, 40)
    for m in ("rk4", "midpoint", "splitting"):
        dig(f"top-{m}", pr.classical(top, m), x_top, 0.1, 100)
    lv = pr.lotka_volterra([[0, 1], [-1, 0]], [1, 2])
    x_lv = np.array([[1.0, 0.8], [1.0, 1.2]])
    for k in (1, 3, 5):
        dig(f"lv-taylor{k}", pr.log_canonical_taylor(lv, k), x_lv, 0.1, 200)
    dig("lv-learned-h01", pr.load_model("lotka_volterra_h01"), x_lv, 0.1, 200)
    for m in ("rk4", "midpoint", "log_splitting", "log_splitting4"):
        dig(f"lv-{m}", pr.log_canonical_classical(lv, m), x_lv, 0.1, 200)
    c = np.zeros((3, 3, 3))
    c[0, 2, 1], c[2, 0, 1] = 2.0, -2.0
    c[1, 2, 0], c[2, 1, 0] = -2.0, 2.0
    aff = pr.affine_poisson_system(
        c, [[0, -1, 0], [1, 0, 0], [0, 0, 0]], {(2, 0, 0): 0.5, (0, 2, 0): 0.5, (0, 4, 0): -1 / 24}
    )
    x_aff = np.array([[0.3, 0.5, 1.0], [1.0, -0.2, 0.4]])
    dig("affine-taylor3", pr.affine_taylor(aff, 3), x_aff, 0.1, 100)
    for m in ("rk4", "midpoint"):
        dig(f"affine-{m}", pr.affine_classical(aff, m), x_aff, 0.1, 100)
    nb = pr.PolynomialPoissonSystem(
        pr.PolynomialBivector.nambu("x1**2 + x2**2 + x3**3/3"), "x1**2/2 + x2**2 + x3**2/3"
    )
    x_nb = np.array([[0.5, 0.4, 0.3], [0.2, -0.3, 0.6]])
    dig("nambu-taylor3", RealizationTaylorIntegrator(nb, 3, tol=1e-12, max_iter=50), x_nb, 0.1, 50)
    for m in ("rk4", "midpoint"):
        dig(f"nambu-{m}", VectorFieldIntegrator(nb, m, tol=1e-12, max_iter=50), x_nb, 0.1, 50)
    return out


def test_every_old_stepper_keeps_its_bits() -> None:
    got = _digests()
    want = {
        **BEFORE,
        **LEARNED_MODELS,
        **AFTER_THE_CASIMIR_FIX,
        **AFTER_THE_PREDICTOR,
        **AFTER_THE_MIDPOINT_SWEEPS,
        **AFTER_THE_SE3_LANES,
        **AFTER_THE_NETWORK_LANES,
        **AFTER_THE_LOG_PREDICTOR,
        **AFTER_THE_FIRST_ORDER_GRADIENT,
        **AFTER_THE_LOG_MIDPOINT_LANES,
        **AFTER_THE_CAYLEY_PREDICTOR,
        **AFTER_THE_SECOND_ORDER_START,
        **AFTER_THE_POLYNOMIAL_LANES,
        **AFTER_THE_SERIES_LANES,
        **AFTER_THE_EXP_SECOND_ORDER_START,
        **AFTER_THE_HESSIAN_STARTS,
        **AFTER_THE_FUSED_NETWORK,
        **AFTER_THE_FACTORED_FIELD,
        **AFTER_THE_NETWORK_START,
        **AFTER_THE_SE3_JACOBIAN,
    }
    assert set(got) == set(want)
    changed = sorted(k for k in want if got[k] != want[k])
    assert not changed, f"rollouts changed: {changed}"


#: The rigid body's RK4 and midpoint rollouts after its field took the factored form.
AFTER_THE_FACTORED_FIELD = {
    "rb-rk4": "8c34fb42f12fd048",
    "rb-midpoint": "8845b80afb8ece07",
}


#: The learned Lotka–Volterra rollout after its Newton start left out the network term and its
#: Jacobian kept the network's Hessian from the first update.
AFTER_THE_NETWORK_START = {
    "lv-learned-h01": "c91d9bfea4fe0cb1",
}


#: The learned heavy top's rollout after the se(3) chart's Jacobian came from closed blocks.
AFTER_THE_SE3_JACOBIAN = {
    "top-learned-h05": "4f8a68bfbf69748f",
}
