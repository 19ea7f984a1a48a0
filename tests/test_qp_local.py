"""The sequential-QP local step (swarmpc.solvers.qp_local), checked against independent answers.

(a) its plan meets the dynamics, input, workspace and speed limits, and (recomputed by exact
    distance) keeps d_min from every copy and obstacle, with the separation actually binding;
(b) with no neighbours and no active constraint it is the unconstrained LQ optimum, solved
    here from the KKT system in numpy (own consensus terms included);
(c) on a local problem recorded from a 2-agent ADMM run (2D head-on swap, separation active) it
    converges to the project's IPOPT local solution of the same OBCA problem.
"""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from conftest import dynamics_error
from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.model.geometry import box_halfspaces, box_signed_distance
from swarmpc.solvers.guesses import pair_guess_blocks
from swarmpc.solvers.qp_local import QPLocalLadder, QPLocalOptions, speed_polytope


def settings(dim: int, **changes) -> OCPSettings:
    """Paper weights, N = 10, dt = 0.1, hard OBCA with d_min = 0.05; no limits unless given."""
    base = dict(dim=dim, horizon=10, dt=0.1, discretization="euler", Q=0.1 * np.eye(2 * dim), R=np.eye(dim),
                Qf=np.eye(2 * dim), collision="hard", d_min=0.05, kappa=1000.0, lower=None, upper=None,
                accel=None, speed=None, obstacles=())
    base.update(changes)
    return OCPSettings(**base)


def straight_guess(state: np.ndarray, s: OCPSettings) -> dict[str, np.ndarray]:
    """The measured state coasting: states (2d, N+1) and zero inputs."""
    A, B = discrete_matrices(s.dim, s.dt, s.discretization)
    states = [state]
    for _ in range(s.horizon):
        states.append(A @ states[-1])
    return {"X": np.array(states).T, "U": np.zeros((s.dim, s.horizon))}


def params_for(s: OCPSettings, state, goal, copies, owner_weight=5.0, rho=10.0) -> dict:
    K = s.num_constrained
    own = straight_guess(state, s)["X"][: s.dim, s.first_constrained_step:]
    params = {"x0": state, "goal": goal, "delta": np.full(s.dim, 0.3), "rho": rho,
              "owner_weight": owner_weight if copies else 0.0, "Z": own, "Y": np.zeros((s.dim, K))}
    for c, z in enumerate(copies):
        params[f"Z{c}"], params[f"Y{c}"] = z, np.zeros((s.dim, K))
    return params


def crossing_problem(dim: int) -> tuple[OCPSettings, dict, dict, list[np.ndarray]]:
    """An agent flying +x at 0.6 m/s (above its 0.55 m/s limit) towards its goal, a box obstacle
    just below its path, one neighbour coming head-on and one standing above the path."""
    pad = [0.0] * (dim - 2)
    obstacle = box_halfspaces(np.array([0.35, -0.2, *[1.0] * (dim - 2)]), np.full(dim, 0.15))
    s = settings(dim, accel=np.full(dim, 1.5), speed=0.55, lower=np.array([-2.0, -0.9, *[0.0] * (dim - 2)]),
                 upper=np.array([2.0, 0.9, *[2.0] * (dim - 2)]), obstacles=(obstacle,))
    start = np.array([-0.4, 0.0, *[1.0] * (dim - 2), 0.6, 0.0, *pad])
    goal = np.array([1.6, 0.0, *[1.0] * (dim - 2), 0.0, 0.0, *pad])
    steps = np.arange(s.first_constrained_step, s.horizon + 1) * s.dt
    head_on = np.array([0.9, 0.05, *[1.0] * (dim - 2)])[:, None] + np.outer(np.r_[-0.5, 0.0, pad], steps)
    above = np.tile(np.array([0.4, 0.62, *[1.0] * (dim - 2)])[:, None], (1, len(steps)))
    copies = [head_on, above]
    guess = straight_guess(start, s)
    guess.update({f"C{c}": z for c, z in enumerate(copies)})
    return s, params_for(s, start, goal, copies), guess, copies


def exact_clearances(s: OCPSettings, X: np.ndarray, copies: list[np.ndarray], deltas: list[float] | None = None,
                     ) -> np.ndarray:
    """Euclidean distances of the constrained positions to every copy's delta box (half-size
    ``deltas[c]``, default 0.3) and to every (box) obstacle, from plain geometry."""
    own = X[: s.dim, s.first_constrained_step:]
    deltas = deltas or [0.3] * len(copies)
    gaps = [box_signed_distance(own - c, np.full((s.dim, 1), h), axis=0) for c, h in zip(copies, deltas, strict=True)]
    for _, g in s.obstacles:
        centre, half = 0.5 * (g[: s.dim] - g[s.dim:]), 0.5 * (g[: s.dim] + g[s.dim:])
        gaps.append(box_signed_distance(own - centre[:, None], half[:, None], axis=0))
    return np.array(gaps)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("pinned", [False, True])
def test_plan_meets_dynamics_limits_and_separation(dim, pinned):
    s, params, guess, copies = crossing_problem(dim)
    fixed = {f"C{c}": z for c, z in enumerate(copies)} if pinned else None
    solution = QPLocalLadder(s).solve(params, guess, fixed, copies=len(copies))
    assert solution.success, solution.status
    X, U = solution.x["X"], solution.x["U"]
    assert dynamics_error(X.T[:, None, :], U.T[:, None, :], s.dt) < 1e-12
    assert np.all(np.abs(U) <= s.accel[:, None])
    own = X[:dim, s.first_constrained_step:]
    assert np.all((own >= s.lower[:, None]) & (own <= s.upper[:, None]))
    speed = np.linalg.norm(X[dim:, 1:], axis=0)
    assert np.all(speed <= s.speed)
    assert speed.max() >= speed_polytope(dim)[1] * s.speed - 1e-4  # the inner speed polytope binds
    held = copies if pinned else [solution.x[f"C{c}"] for c in range(len(copies))]
    if pinned:
        np.testing.assert_array_equal(held, copies)
    clearance = exact_clearances(s, X, held)
    assert clearance.min() >= s.d_min
    assert clearance.min() <= s.d_min + 1e-3  # the separation binds: the check is not vacuous


@pytest.mark.parametrize("dim", [2, 3])
def test_each_copy_keeps_its_own_pair_delta(dim):
    """``delta`` (d, n): one Delta_ij per copy (the two bodies' sum). The head-on neighbour's
    larger box binds the plan at d_min from that box; a (d, 1) column is every copy's Delta."""
    s, params, guess, copies = crossing_problem(dim)
    ladder = QPLocalLadder(s)
    wide = ladder.solve({**params, "delta": np.column_stack([np.full(dim, 0.4), np.full(dim, 0.3)])}, guess,
                        copies=2)
    assert wide.success, wide.status
    held = [wide.x[f"C{c}"] for c in range(2)]
    clearance = exact_clearances(s, wide.x["X"], held, [0.4, 0.3])
    assert clearance.min() >= s.d_min
    assert clearance[0].min() <= s.d_min + 1e-3  # the wider pair binds
    narrow = ladder.solve(params, guess, copies=2)
    as_column = ladder.solve({**params, "delta": np.full((dim, 1), 0.3)}, guess, copies=2)
    np.testing.assert_allclose(as_column.x["X"], narrow.x["X"], atol=1e-9)
    narrow_held = [narrow.x[f"C{c}"] for c in range(2)]
    assert exact_clearances(s, narrow.x["X"], narrow_held, [0.4, 0.3])[0].min() < s.d_min  # 0.4 mattered


def test_soft_pairs_keep_dynamics_and_price_the_shortfall():
    """A neighbour pinned right on the agent's start: no plan clears it, the soft form flies the
    least-violating plan and reports the slack it needs."""
    s = settings(2, collision="hard", accel=np.full(2, 1.0))
    start = np.array([0.0, 0.0, 0.3, 0.0])
    sitting = np.tile(np.array([[0.1], [0.05]]), (1, s.num_constrained))
    params = params_for(s, start, np.array([1.0, 0.0, 0.0, 0.0]), [sitting])
    guess = {**straight_guess(start, s), "C0": sitting}
    hard = QPLocalLadder(s).solve(params, guess, {"C0": sitting}, copies=1)
    assert not hard.success
    soft = QPLocalLadder(s, pair_collision="soft").solve(params, guess, {"C0": sitting}, copies=1)
    assert soft.success, soft.status
    X = soft.x["X"]
    assert dynamics_error(X.T[:, None, :], soft.x["U"].T[:, None, :], s.dt) < 1e-12
    gap = exact_clearances(s, X, [sitting])[0]
    np.testing.assert_allclose(soft.x["A0"][0], np.maximum(s.d_min - gap, 0.0), atol=1e-9)
    assert soft.x["A0"].max() > 0


def lq_by_kkt(s: OCPSettings, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """The equality-constrained LQ problem (tracking + own consensus terms, initial state and
    dynamics as equalities) solved from its KKT system; returns X (2d, N+1) and U (d, N)."""
    d, N, first = s.dim, s.horizon, s.first_constrained_step
    A, B = discrete_matrices(d, s.dt, s.discretization)
    nx, nu = 2 * d * (N + 1), d * N
    H, f = np.zeros((nx + nu, nx + nu)), np.zeros(nx + nu)
    rho_own = params["rho"] * params["owner_weight"]
    for k in range(N + 1):
        W = s.Q if k < N else s.Qf
        idx = slice(2 * d * k, 2 * d * (k + 1))
        H[idx, idx] += 2 * W
        f[idx] -= 2 * W @ params["goal"]
        if k >= first:
            pos = slice(2 * d * k, 2 * d * k + d)
            H[pos, pos] += rho_own * np.eye(d)
            f[pos] += params["Y"][:, k - first] - rho_own * params["Z"][:, k - first]
    for k in range(N):
        idx = slice(nx + d * k, nx + d * (k + 1))
        H[idx, idx] += 2 * s.R
    C, b = np.zeros((2 * d * (N + 1), nx + nu)), np.zeros(2 * d * (N + 1))
    C[: 2 * d, : 2 * d], b[: 2 * d] = np.eye(2 * d), params["x0"]
    for k in range(N):
        rows = slice(2 * d * (k + 1), 2 * d * (k + 2))
        C[rows, 2 * d * (k + 1): 2 * d * (k + 2)] = np.eye(2 * d)
        C[rows, 2 * d * k: 2 * d * (k + 1)] = -A
        C[rows, nx + d * k: nx + d * (k + 1)] = -B
    kkt = np.block([[H, C.T], [C, np.zeros((len(b), len(b)))]])
    z = np.linalg.solve(kkt, np.concatenate([-f, b]))
    return z[:nx].reshape(N + 1, 2 * d).T, z[nx: nx + nu].reshape(N, d).T


@pytest.mark.parametrize("consensus", [False, True])
def test_unconstrained_step_is_the_lq_optimum(consensus):
    s = settings(3, accel=np.full(3, 50.0), lower=np.full(3, -50.0), upper=np.full(3, 50.0))  # never active
    rng = np.random.default_rng(4)
    state = np.r_[rng.uniform(-1, 1, 3), rng.uniform(-0.5, 0.5, 3)]
    goal = np.r_[rng.uniform(-1, 1, 3), np.zeros(3)]
    params = params_for(s, state, goal, [])
    if consensus:  # the own block of an agent that others hold copies of
        params.update(owner_weight=5.0, Z=params["Z"] + rng.normal(0, 0.1, params["Z"].shape),
                      Y=rng.normal(0, 0.3, params["Y"].shape))
    solution = QPLocalLadder(s).solve(params, straight_guess(state, s), copies=0)
    assert solution.success, solution.status
    X, U = lq_by_kkt(s, params)
    np.testing.assert_allclose(solution.x["X"], X, atol=1e-10)
    np.testing.assert_allclose(solution.x["U"], U, atol=1e-10)


RECORDED = {
    # agent 0's local problem in an ADMM iteration of MPC step 12 of a 2D head-on swap of two agents
    # (starts (-1, 0.05) and (1, -0.05), delta 0.3, accel 1, workspace +-3): its separation from the
    # copy is active at the last steps
    "x0": [-0.589048, 0.041781, 0.40437, -0.008087],
    "goal": [1.5, 0.0, 0.0, 0.0],
    "delta": [0.3, 0.3],
    "rho": 10.0,
    "owner_weight": 5.0,
    "Z": [[-0.507253, -0.465218, -0.422726, -0.379976, -0.337146, -0.29439, -0.251837, -0.209593, -0.17485],
          [0.040145, 0.039304, 0.038455, 0.0376, 0.036743, 0.035888, 0.035037, 0.034192, 0.033497]],
    "Y": [[-0.001813, -0.00528, -0.010215, -0.016426, -0.023697, -0.031771, -0.040329, -0.04897, 0.298462],
          [0.000036, 0.000106, 0.000204, 0.000329, 0.000474, 0.000635, 0.000807, 0.000979, -0.005969]],
    "Z0": [[0.507253, 0.465218, 0.422726, 0.379976, 0.337146, 0.29439, 0.251837, 0.209593, 0.17485],
           [-0.040145, -0.039304, -0.038455, -0.0376, -0.036743, -0.035888, -0.035037, -0.034192, -0.033497]],
    "Y0": [[-0.001813, -0.00528, -0.010215, -0.016426, -0.023697, -0.031771, -0.040329, -0.04897, 0.298462],
           [0.000036, 0.000106, 0.000204, 0.000329, 0.000474, 0.000635, 0.000807, 0.000979, -0.005969]],
}
RECORDED_GUESS = {  # the agent's previous ADMM iterate
    "X": [[-0.589048, -0.548611, -0.507291, -0.465327, -0.422936, -0.380313, -0.337631, -0.295038, -0.25266,
           -0.210591, -0.1689],
          [0.041781, 0.040972, 0.040146, 0.039307, 0.038459, 0.037606, 0.036753, 0.035901, 0.035053, 0.034212,
           0.033378],
          [0.40437, 0.413197, 0.41964, 0.423913, 0.426232, 0.426823, 0.425923, 0.423787, 0.420686, 0.416915, 0.412787],
          [-0.008087, -0.008264, -0.008393, -0.008478, -0.008525, -0.008536, -0.008518, -0.008476, -0.008414,
           -0.008338, -0.008256]],
    "U": [[0.088263, 0.064433, 0.04273, 0.023192, 0.005907, -0.008999, -0.021365, -0.031005, -0.037713, -0.041279],
          [-0.001765, -0.001289, -0.000855, -0.000464, -0.000118, 0.00018, 0.000427, 0.00062, 0.000754, 0.000826]],
    "C0": [[0.507062, 0.464672, 0.421676, 0.378293, 0.334723, 0.291146, 0.247725, 0.204601, 0.204601],
           [-0.040141, -0.039293, -0.038434, -0.037566, -0.036694, -0.035823, -0.034954, -0.034092, -0.034092]],
}


def test_converges_to_the_ipopt_local_solution():
    s = settings(2, accel=np.full(2, 1.0), lower=np.full(2, -3.0), upper=np.full(2, 3.0))
    params = {k: np.asarray(v, float) if isinstance(v, list) else v for k, v in RECORDED.items()}
    guess = {k: np.asarray(v, float) for k, v in RECORDED_GUESS.items()}
    own = guess["X"][:2, s.first_constrained_step:]
    seeded = {**guess, **pair_guess_blocks("0", (own - guess["C0"]).T, params["delta"], s)}
    ipopt = build_local(s, 1).solve(params, seeded)
    assert ipopt.success, ipopt.status
    separation = box_signed_distance(ipopt.x["X"][:2, 2:] - ipopt.x["C0"], params["delta"][:, None], axis=0)
    assert separation.min() == pytest.approx(s.d_min, abs=1e-6)  # the OBCA constraint is active
    qp = QPLocalLadder(s, options=QPLocalOptions(margin=1e-9)).solve(params, guess, copies=1)
    assert qp.success, qp.status
    np.testing.assert_allclose(qp.x["X"], ipopt.x["X"], atol=1e-6)
    np.testing.assert_allclose(qp.x["C0"], ipopt.x["C0"], atol=1e-6)
    assert qp.cost == pytest.approx(ipopt.cost, rel=1e-8)


def test_a_solution_vector_restarts_the_same_problem_at_its_fixed_point():
    s, params, guess, copies = crossing_problem(2)
    ladder = QPLocalLadder(s)
    first = ladder.solve(params, guess, copies=2)
    again = ladder.solve(params, first.x_vec, copies=2, duals=(first.lam_x, first.lam_g))
    assert again.success and again.iterations == 1  # one QP round: the certificates are settled
    np.testing.assert_allclose(again.x["X"], first.x["X"], atol=1e-7)
    rebuilt = pickle.loads(pickle.dumps(ladder))  # a worker process gets the recipe, builds its own
    np.testing.assert_allclose(rebuilt.solve(params, guess, copies=2).x["X"], first.x["X"], atol=1e-9)
    with pytest.raises(NotImplementedError):
        ladder.solve(params, guess, {"Xc0": np.zeros((4, 11))}, copies=2)


@pytest.mark.parametrize("dim", [2, 3])
def test_speed_polytope_is_inside_the_ball(dim):
    from scipy.spatial import HalfspaceIntersection

    normals, ratio = speed_polytope(dim)
    vertices = HalfspaceIntersection(np.hstack([normals, -ratio * np.ones((len(normals), 1))]),
                                     np.zeros(dim)).intersections
    assert np.linalg.norm(vertices, axis=1).max() <= 1.0 + 1e-12
    assert ratio > (0.98 if dim == 2 else 0.88)


def test_a_repair_pass_starts_from_the_free_copy_answer():
    """LocalAgent hands a repair pass (copies pinned) its last answer's vector, laid out for the
    problem with free copies: the step takes the plan from it."""
    s, params, guess, copies = crossing_problem(2)
    ladder = QPLocalLadder(s)
    free = ladder.solve(params, guess, copies=2)
    pinned = ladder.solve(params, free.x_vec, {f"C{c}": z for c, z in enumerate(copies)}, copies=2)
    assert pinned.success, pinned.status
    assert exact_clearances(s, pinned.x["X"], copies).min() >= s.d_min
