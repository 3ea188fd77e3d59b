"""Implicit differentiation of solutions against independent references.

* a dense KKT solve of a quadratic program with a known active set, differentiated by plain autograd
  through ``torch.linalg.solve`` (no Riccati, no implicit function theorem);
* ``torch.autograd.gradcheck`` (central differences of re-solves) in float64;
* per-instance solves against the batch; the non-converged policy; float32 against float64.
"""

import warnings

import pytest
import torch
from small_problems import pendulum10
from torch.func import hessian, jacrev

import torchtraj as tt
from torchtraj.core.batching import rollout
from torchtraj.core.constraints import Constraints
from torchtraj.core.solution import History
from torchtraj.differentiation import implicit
from torchtraj.solvers.altro.options import ALTROOptions
from torchtraj.solvers.altro.projection import ProjectionOptions

F64 = torch.float64


# --------------------------------------------------------------------------- small problems
def oscillator(dtype=F64, u_max=None, v_max=None, goal_constraint=False, N=8):
    """A damped linear oscillator with quadratic costs: every constraint linear, so with a fixed
    active set the solution is one linear solve. ``v_max`` bounds the velocity on knots 1..N-1
    (a state-only row); ``u_max`` the control."""
    dt = 0.2

    def dynamics(x, u, p):
        return torch.stack([x[0] + dt * x[1], x[1] + dt * (-p["stiffness"] * x[0] - 0.2 * x[1] + u[0])])

    def stage_cost(x, u, p):
        e = x - p["goal"]
        return 0.5 * p["w"] * (e @ e) + 0.5 * p["r"] * (u @ u)

    def terminal_cost(x, p):
        e = x - p["goal"]
        return 2.5 * (e @ e)

    def t(v):
        return torch.tensor(v, dtype=dtype)

    params = {"stiffness": t(1.5), "goal": t([1.0, 0.0]), "w": t(1.0), "r": t(0.1),
              "v_max": t(0.0 if v_max is None else v_max)}
    return tt.Problem(
        dynamics=dynamics, stage_cost=stage_cost, terminal_cost=terminal_cost,
        x0=t([0.0, 0.0]), horizon=N, nu=1, params=params,
        state_ineq=(lambda x, p: (x[1] - p["v_max"]).reshape(1)) if v_max is not None else None,
        terminal_eq=(lambda x, p: x - p["goal"]) if goal_constraint else None,
        u_upper=None if u_max is None else t([u_max]),
        u_lower=None if u_max is None else t([-u_max]),
        name="oscillator",
    )


def dense_active_set_qp(problem, x0, params, max_rounds=30):
    """Solve the (convex) QP ``problem`` for one instance by a primal-dual active-set loop on dense KKT
    systems. Returns ``X, U, y, active`` where ``solve(active)`` below reproduces them differentiably."""
    cons = Constraints(problem)
    N, nx, nu = problem.N, problem.nx, problem.nu

    def unpack(z):
        X = z[: (N + 1) * nx].reshape(N + 1, nx)
        return X, z[(N + 1) * nx:].reshape(N, nu)

    def cost(z, p):
        X, U = unpack(z)
        stage = torch.stack([problem.stage_cost(X[k], U[k], p) for k in range(N)]).sum()
        return stage + problem.terminal_cost(X[N], p)

    def equalities(z, x0, p):
        X, U = unpack(z)
        rows = [x0 - X[0]] + [problem.dynamics(X[k], U[k], p) - X[k + 1] for k in range(N)]
        rows += [cons.stage_eq(X[k], U[k], p) for k in range(N)]
        rows.append(cons.terminal_eq(X[N], p))
        return torch.cat(rows)

    def inequalities(z, p):
        X, U = unpack(z)
        mask = cons.ineq_knot_mask
        rows = [cons.stage_ineq(X[k], U[k], p)[mask[k] > 0] for k in range(N)] + [cons.terminal_ineq(X[N], p)]
        return torch.cat(rows)

    nz = (N + 1) * nx + N * nu

    def solve(active, x0, p):
        z0 = torch.zeros(nz, dtype=x0.dtype)
        H, h = hessian(cost)(z0, p), jacrev(cost)(z0, p)
        E = jacrev(equalities)(z0, x0, p)
        e = equalities(z0, x0, p)
        if active.any():
            E = torch.cat([E, jacrev(inequalities)(z0, p)[active]])
            e = torch.cat([e, inequalities(z0, p)[active]])
        K = torch.cat([torch.cat([H, E.T], 1), torch.cat([E, torch.zeros(len(e), len(e), dtype=x0.dtype)], 1)])
        sol = torch.linalg.solve(K, -torch.cat([h, e]))
        return sol[:nz], sol[nz:]

    m = inequalities(torch.zeros(nz, dtype=x0.dtype), params).shape[0]
    active = torch.zeros(m, dtype=torch.bool)
    with torch.no_grad():
        for _ in range(max_rounds):
            z, y = solve(active, x0, params)
            g = inequalities(z, params)
            mu = torch.zeros(m, dtype=x0.dtype)
            mu[active] = y[y.shape[0] - int(active.sum()):]
            new = (active & (mu >= 0)) | (g > 1e-12)
            if torch.equal(new, active):
                break
            active = new
        else:
            raise AssertionError("the active-set loop did not settle")
    return solve, active, g, mu, unpack


def as_solution(X, U, method="altro"):
    """A converged one-instance Solution holding ``X``, ``U`` (for attach_gradients)."""
    B = X.shape[0]
    zeros = torch.zeros(B, dtype=X.dtype)
    return tt.Solution(X=X, U=U, K=torch.zeros(B, U.shape[1], U.shape[2], X.shape[2], dtype=X.dtype), cost=zeros,
                       max_violation=zeros, status=torch.zeros(B, dtype=torch.long), iterations=zeros.long(),
                       history=History.from_rows([]), method=method)


# ---------------------------------------------------------------- the adjoint against dense KKT
QP_CASES = {
    "control_bounds": dict(u_max=0.6),
    "state_inequality": dict(v_max=0.35),
    "goal_equality_and_bounds": dict(u_max=1.6, goal_constraint=True),
    "all": dict(u_max=2.0, v_max=0.7, goal_constraint=True),
}


@pytest.mark.parametrize("case", list(QP_CASES))
def test_adjoint_matches_autograd_through_a_dense_kkt_solve(case):
    problem = oscillator(**QP_CASES[case])
    names = ["stiffness", "goal", "w", "r", "v_max"]
    leaves = {n: problem.params[n].clone().requires_grad_(True) for n in names}
    x0 = torch.tensor([0.3, -0.2], dtype=F64, requires_grad=True)
    solve, active, g, mu, unpack = dense_active_set_qp(problem, x0.detach(), {k: v.detach() for k, v in leaves.items()})
    # the case really has active and inactive inequality rows, strictly complementary
    if problem.constraint_sizes()["state_ineq"] or problem.u_upper is not None:
        assert 0 < int(active.sum()) < active.numel()
        assert mu[active].min() > 1e-6 and g[~active].max() < -1e-6
    # reference: autograd through the dense solve with the active set fixed
    z, y = solve(active, x0, leaves)
    X_ref, U_ref = unpack(z)
    gen = torch.Generator().manual_seed(0)
    X_bar = torch.randn(X_ref.shape, generator=gen, dtype=F64)
    U_bar = torch.randn(U_ref.shape, generator=gen, dtype=F64)
    ref = torch.autograd.grad((X_ref * X_bar).sum() + (U_ref * U_bar).sum(), [x0, *leaves.values()],
                              allow_unused=True)
    # implicit: the same point as a converged Solution
    p = problem.with_params(**leaves)
    sol = implicit.attach_gradients(p, x0.unsqueeze(0), p.batched_params(1),
                                    as_solution(X_ref.detach().unsqueeze(0), U_ref.detach().unsqueeze(0)))
    assert torch.allclose(sol.X[0], X_ref, atol=1e-12) and torch.allclose(sol.U[0], U_ref, atol=1e-12)
    got = torch.autograd.grad((sol.X[0] * X_bar).sum() + (sol.U[0] * U_bar).sum(), [x0, *leaves.values()],
                              allow_unused=True)
    for name, a, b, leaf in zip(["x0"] + names, got, ref, [x0, *leaves.values()]):
        a = torch.zeros_like(leaf) if a is None else a
        b = torch.zeros_like(leaf) if b is None else b
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-9 * (1 + b.abs().max())), (name, a, b)


def test_kkt_multipliers_match_the_dense_solve():
    problem = oscillator(**QP_CASES["all"])
    x0 = torch.tensor([0.3, -0.2], dtype=F64)
    solve, active, _, _, unpack = dense_active_set_qp(problem, x0, problem.params)
    z, y = solve(active, x0, problem.params)
    X, U = unpack(z)
    kkt = implicit.kkt_system(problem, x0.unsqueeze(0), X.unsqueeze(0), U.unsqueeze(0), problem.batched_params(1))
    N, nx = problem.N, problem.nx
    lam = y[: (N + 1) * nx].reshape(N + 1, nx)
    assert torch.allclose(kkt.multipliers.costate[0], lam, atol=1e-10)
    # the multipliers of the active inequality rows, in the dense solve's order (knot by knot)
    cons = Constraints(problem)
    rows = kkt.multipliers.nu[0][cons.ineq_knot_mask > 0]
    mu = torch.zeros(active.numel(), dtype=F64)
    mu[active] = y[y.shape[0] - int(active.sum()):]
    goal = y[(N + 1) * nx:(N + 2) * nx]  # the goal rows come before the active inequality rows
    assert int(active.sum()) > 0 and torch.allclose(rows, mu, atol=1e-10)
    assert torch.allclose(kkt.multipliers.nuN[0], goal, atol=1e-10)


# ------------------------------------------------------------------- gradcheck through tt.solve
def pendulum(N=10, **changes):
    return pendulum10(N, **changes)


def car(N=10):
    """A unicycle with a speed ``gain`` (a dynamics parameter) passing a circle obstacle of radius 0.3."""
    def dynamics(x, u, p):
        v = p["gain"] * u[0]
        return torch.stack([v * torch.cos(x[2]), v * torch.sin(x[2]), u[1]])

    def stage_cost(x, u, p):
        e = x - p["goal"]
        return 0.5 * p["w"] * (e @ e) + 0.25 * (u @ u)

    def terminal_cost(x, p):
        e = x - p["goal"]
        return 5.0 * (e @ e)

    def outside(x, p):
        c = p["obstacle"]
        return (0.09 - (x[0] - c[0]) ** 2 - (x[1] - c[1]) ** 2).reshape(1)

    params = {"gain": torch.tensor(1.0, dtype=F64), "goal": torch.tensor([2.0, 0.0, 0.0], dtype=F64),
              "w": torch.tensor(0.1, dtype=F64), "obstacle": torch.tensor([1.0, 0.1], dtype=F64)}
    return tt.Problem(dynamics=tt.rk4(dynamics, 0.2), stage_cost=stage_cost, terminal_cost=terminal_cost,
                      x0=torch.zeros(3, dtype=F64), horizon=N, nu=2, params=params, state_ineq=outside,
                      u_init=torch.tensor([0.5, 0.0], dtype=F64), name="car10")


def pendulum_theta(problem):
    """x0, mass (dynamics), Q (a cost weight) and goal packed in one vector; and its unpacking."""
    theta = torch.cat([torch.tensor([0.1, 0.2], dtype=F64), problem.params["mass"].reshape(1),
                       problem.params["Q"].reshape(-1), problem.params["goal"]])

    def unpack(th):
        return th[:2], dict(mass=th[2], Q=th[3:7].reshape(2, 2), goal=th[7:9])

    return theta, unpack


def car_theta(problem):
    """x0, gain (dynamics), w (a cost weight), goal and the obstacle centre in one vector."""
    p = problem.params
    theta = torch.cat([torch.tensor([0.0, -0.05, 0.0], dtype=F64), p["gain"].reshape(1), p["w"].reshape(1),
                       p["goal"], p["obstacle"]])

    def unpack(th):
        return th[:3], dict(gain=th[3], w=th[4], goal=th[5:8], obstacle=th[8:10])

    return theta, unpack


GRADCHECK_CASES = {
    "unconstrained": (lambda: pendulum(), pendulum_theta, "ilqr"),
    "control_bounds": (lambda: pendulum(u_lower=torch.tensor([-3.0], dtype=F64),
                                        u_upper=torch.tensor([3.0], dtype=F64)), pendulum_theta, "altro"),
    "goal_equality": (lambda: pendulum(terminal_eq=lambda x, p: x - p["goal"]), pendulum_theta, "altro"),
    "circle_obstacle": (car, car_theta, "altro"),
}


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if c == "circle_obstacle" else c
                                  for c in GRADCHECK_CASES])  # the car's ALTRO re-solves: half a minute
def test_gradcheck_through_solve(case):
    """gradcheck (central differences of whole re-solves) of X, U and cost with respect to x0, a
    dynamics parameter, a cost weight, the goal and, for the car, the obstacle centre, packed in one
    vector so that fast mode checks one random direction of all of them at once."""
    make, pack, method = GRADCHECK_CASES[case]
    problem = make()
    theta, unpack = pack(problem)

    def layer(th):
        x0, params = unpack(th)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # ilqr on ... (no constraints here)
            sol = tt.solve(problem.with_params(**params), x0, method=method)
        assert bool(sol.converged.all())
        return sol.X, sol.U, sol.cost

    theta.requires_grad_(True)
    X, U, _ = layer(theta)
    # the constraints this case is about are active at the solution
    cons = Constraints(problem)
    values = cons.evaluate(X.detach(), U.detach(), problem.batched_params(1))
    if case == "control_bounds":
        assert int((values.ineq > -1e-9).sum()) >= 1 and int((values.ineq < -1e-3).sum()) >= 1
    if case == "circle_obstacle":
        assert int((values.ineq > -1e-9).sum()) >= 1
    assert torch.autograd.gradcheck(layer, (theta,), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


# ------------------------------------------------------------------- batches, failures, float32
def test_batch_gradients_equal_single_instance_gradients():
    """Three instances with their own x0 and mass solved together: each one's gradients equal those of
    the instance solved alone (with control bounds active, through ALTRO)."""
    problem = pendulum(u_lower=torch.tensor([-3.0], dtype=F64), u_upper=torch.tensor([3.0], dtype=F64))
    x0s = torch.tensor([[0.1, 0.2], [0.3, -0.1], [-0.2, 0.0]], dtype=F64)
    masses = torch.tensor([1.0, 1.2, 0.9], dtype=F64)
    Q = problem.params["Q"]

    def grads(x0, mass):
        x0, mass, q = x0.clone().requires_grad_(True), mass.clone().requires_grad_(True), Q.clone().requires_grad_(True)
        sol = tt.solve(problem.with_params(mass=mass, Q=q), x0, method="altro")
        assert bool(sol.converged.all())
        loss = sol.U.sum() + sol.X[:, -5:].pow(2).sum() + sol.cost.sum()
        return torch.autograd.grad(loss, [x0, mass, q])

    gx, gm, gq = grads(x0s, masses)
    for b in range(3):
        sx, sm, sq = grads(x0s[b], masses[b:b + 1])
        assert torch.allclose(gx[b], sx, rtol=1e-8, atol=1e-10)
        assert torch.allclose(gm[b], sm[0], rtol=1e-8, atol=1e-10)
        gq = gq - sq
    assert gq.abs().max() < 1e-8 * (1 + Q.abs().max())  # the shared weight's gradient is the sum


def test_non_converged_instances_get_zero_gradient_and_a_warning():
    """An instance with a NaN initial state does not converge: its gradients are zero, a RuntimeWarning
    names it, and the other instance's gradients are those of its solve alone."""
    problem = pendulum()
    x0 = torch.tensor([[0.1, 0.2], [float("nan"), 0.0]], dtype=F64, requires_grad=True)
    mass = torch.tensor([1.0, 1.0], dtype=F64, requires_grad=True)
    with pytest.warns(RuntimeWarning, match=r"instance\(s\) \[1\] did not converge"):
        sol = tt.solve(problem.with_params(mass=mass), x0)
    assert sol.status.tolist() == [tt.Status.CONVERGED, tt.Status.NON_FINITE]
    gx, gm = torch.autograd.grad(sol.U.nan_to_num().sum() + sol.cost.nan_to_num().sum(), [x0, mass])
    assert bool((gx[1] == 0).all()) and gm[1] == 0
    x1 = x0[:1].detach().clone().requires_grad_(True)
    m1 = mass[:1].detach().clone().requires_grad_(True)
    alone = tt.solve(problem.with_params(mass=m1), x1)
    ax, am = torch.autograd.grad(alone.U.sum() + alone.cost.sum(), [x1, m1])
    assert torch.allclose(gx[0], ax[0], rtol=1e-9) and torch.allclose(gm[0], am[0], rtol=1e-9)
    assert gx[0].abs().max() > 0


def test_float32_gradients_agree_with_float64():
    problem = pendulum(u_lower=torch.tensor([-3.0], dtype=F64), u_upper=torch.tensor([3.0], dtype=F64))
    out = {}
    for dtype in (torch.float64, torch.float32):
        p = problem.to(dtype)
        x0 = torch.tensor([0.1, 0.2], dtype=dtype, requires_grad=True)
        mass = p.params["mass"].clone().requires_grad_(True)
        # default options in both dtypes: ALTRO's tolerances are met at float32's resolution
        sol = tt.solve(p.with_params(mass=mass), x0, method="altro")
        assert bool(sol.converged.all()) and sol.U.dtype == dtype
        out[dtype] = torch.autograd.grad(sol.U.sum() + sol.X[:, -5:].pow(2).sum(), [x0, mass])
    for a, b in zip(out[torch.float32], out[torch.float64]):
        assert torch.allclose(a.double(), b, rtol=2e-3, atol=2e-3 * b.abs().max())


def test_ipm_float32_gradients_through_an_active_obstacle_agree_with_float64():
    """The interior-point method's multipliers are positive on every row: in float32 the active set
    must still be the rows at the obstacle, not every row with a positive multiplier."""
    problem = car()
    out = {}
    for dtype in (torch.float64, torch.float32):
        p = problem.to(dtype)
        x0 = torch.tensor([[0.0, -0.05, 0.0], [0.0, 0.05, 0.0]], dtype=dtype, requires_grad=True)
        obstacle = p.params["obstacle"].clone().requires_grad_(True)
        sol = tt.solve(p.with_params(obstacle=obstacle), x0, method="ipm")
        assert bool(sol.converged.all())
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            out[dtype] = torch.autograd.grad(sol.U.sum() + sol.X[:, -5:].pow(2).sum(), [x0, obstacle])
    for a, b in zip(out[torch.float32], out[torch.float64]):
        assert b.abs().max() > 0.1
        assert torch.allclose(a.double(), b, rtol=1e-2, atol=1e-2 * b.abs().max())


def test_refine_reaches_round_off_stationarity():
    """iLQR at Altro.jl's tolerances (``ILQROptions.fast``) stops with a reduced gradient of about 2e-3 here,
    which the KKT certificate reports as STALLED; the Newton refinement makes the reduced gradient, computed
    independently by autograd through a rollout, vanish to round-off."""
    problem = pendulum()
    sol = tt.solve(problem, options=tt.ILQROptions.fast())
    assert sol.status.tolist() == [tt.Status.STALLED]
    params = problem.batched_params(1)
    x0 = problem.x0.unsqueeze(0)

    def reduced_gradient(U):
        U = U.detach().clone().requires_grad_(True)
        J = tt.kkt.total_cost(problem, rollout(problem.dynamics, x0, U, params), U, params)
        return torch.autograd.grad(J.sum(), U)[0]

    refined = implicit.refine(problem, x0, sol.X, sol.U, params, constrained=False)
    before, after = reduced_gradient(sol.U).abs().max(), reduced_gradient(refined.U).abs().max()
    assert before > 1e-4 and after < 1e-13, (before, after)
    assert int(refined.steps[0]) >= 1 and refined.kkt is not None


def test_fd_check_by_instance_leaves_out_a_weakly_active_row_that_switches():
    """The --grad benchmark's check by instance (torchtraj.bench.grad.fd_by_instance): instance 1 starts
    where its velocity peak touches v_max exactly (a weakly active row, zero multiplier). The implicit
    gradient holds the row active and gives the one-sided derivative on the active side, as the module
    docstring says; raising v_max frees the row, so the central difference is half of it (the free
    side does not depend on v_max). The check leaves that instance out and says why; on instance 0
    (row strongly active) both agree. The shared parameter's gradient is the sum of its shares."""
    from torchtraj.bench import grad as bench_grad

    x0 = torch.tensor([[0.0, 0.0], [0.5, 0.0]], dtype=F64)
    free = tt.solve(oscillator(v_max=10.0), x0, method="altro")
    peaks = free.X[:, 1:-1, 1].amax(-1)
    assert float(peaks[0]) > float(peaks[1]) + 0.1  # instance 0 is held back by v_max = peak of instance 1
    problem = oscillator(v_max=float(peaks[1]))
    g = torch.Generator().manual_seed(0)
    Xbar = torch.randn(2, 9, 2, generator=g, dtype=F64)
    Ubar = torch.randn(2, 8, 1, generator=g, dtype=F64)

    def loss(sol):  # linear in (X, U): one-sided differences are exact on a fixed active set
        return (sol.X * Xbar).flatten(1).sum(-1) + (sol.U * Ubar).flatten(1).sum(-1)

    theta = {"x0": x0, "v_max": problem.params["v_max"]}
    dirs = {"x0": torch.tensor([[1.0, -0.5], [0.3, 0.2]], dtype=F64), "v_max": torch.tensor(1.0, dtype=F64)}
    nominal = bench_grad.solve_by_instance(problem, theta, "altro", None, loss)
    nominal.loss.sum().backward()
    analytic = bench_grad.directional(nominal.inputs, dirs)
    reference = bench_grad.resolved(nominal)
    assert reference.active.sum(-1).tolist() == [6, 1]

    def resolve(th):
        return bench_grad.resolved(bench_grad.solve_by_instance(problem, th, "altro", None, loss))

    # 1e-2: far outside the active tolerances, and exact on the linear pieces
    check = bench_grad.fd_by_instance(resolve, theta, dirs, analytic, reference, step=1e-2)
    assert check.kept.tolist() == [True, False]
    assert torch.allclose(check.fd["v_max"][1], analytic["v_max"][1] / 2, rtol=1e-8)
    assert torch.allclose(check.fd["v_max"][0], analytic["v_max"][0], rtol=1e-8)
    assert check.agreement() < 1e-9 and check.agreement(only_kept=False) > 0.1
    text = check.describe()
    assert text.startswith("FD over 1/2 instances (left out #1: another active set in the ") and "v_max+" in text
    assert "over all 2: " in text

    shared = problem.params["v_max"].clone().requires_grad_(True)
    sol = tt.solve(problem.with_params(v_max=shared), x0, method="altro")
    (g_shared,) = torch.autograd.grad(loss(sol).sum(), [shared])
    assert torch.allclose(nominal.inputs["v_max"].grad.sum(), g_shared, rtol=1e-12)


# ------------------------------------------- pendulum with bang-bang arcs and a goal equality
def _pendulum_mass_solve(rows, options, mass=1.2):
    """Solve the benchmark pendulum (|u| ≤ 3, x_N = goal) from seed 0's x0 ``rows`` with a per-instance
    mass leaf; returns the solution, the leaf and the per-instance loss ``Σ U²``."""
    x0 = tt.problems.sample_x0("pendulum", 8, seed=0)[rows]
    leaf = torch.full((len(rows),), mass, dtype=F64, requires_grad=True)
    sol = tt.solve(tt.problems.get("pendulum").with_params(mass=leaf), x0, method="altro", options=options)
    return sol, leaf, (sol.U ** 2).flatten(1).sum(-1)


@pytest.mark.slow  # central differences of full pendulum re-solves
def test_pendulum_instances_refined_from_reference_accuracy_match_central_differences():
    """Instances 0 and 4 of seed 0 at mass 1.2: reference-accuracy ALTRO stops 0.13 (in U) short of the
    KKT point (a Newton step of 0.12 that refinement used to reject as too large, leaving gradients 7 %
    and 25 % off). Refined to the KKT point, the gradient of Σ U² with respect to the mass agrees, with
    no warning, with central differences (mass ± 1e-6) of warm re-solves refined to their KKT points,
    whose active sets are the nominal one."""
    problem = tt.problems.get("pendulum")
    options = tt.problems.altro_options("pendulum")
    rows = [0, 4]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        sol, leaf, loss = _pendulum_mass_solve(rows, options)
        (grad,) = torch.autograd.grad(loss.sum(), [leaf])
    assert bool(sol.converged.all())
    x0 = tt.problems.sample_x0("pendulum", 8, seed=0)[rows]
    U0 = sol.U.detach()

    def exact(mass):  # the KKT point near U0: a warm re-solve, refined to round-off
        p = problem.with_params(mass=torch.full((2,), mass, dtype=F64))
        params = p.batched_params(2)
        s = tt.solve(p, x0, method="altro", options=options, U0=U0)
        r = implicit.refine(p, x0, s.X, s.U, params, steps=10, solver_multipliers=s.multipliers)
        assert bool(r.stationary.all()) and float(r.residual.max()) < 1e-12
        return (r.U ** 2).flatten(1).sum(-1), r.active[0]

    nominal, active = exact(1.2)
    assert torch.allclose(nominal, loss.detach(), rtol=1e-12)  # the point that was differentiated
    assert int(active.sum()) == 18 + 21 and bool((active.sum((1, 2)) < 50).all())  # bang-bang arcs
    h = 1e-6
    (up, a_up), (down, a_down) = exact(1.2 + h), exact(1.2 - h)
    assert bool((a_up == active).all() and (a_down == active).all())
    fd = (up - down) / (2 * h)
    assert torch.allclose(grad, fd, rtol=1e-6), (grad, fd)
    assert float(grad.abs().min()) > 100


def test_pendulum_solves_stopped_short_of_a_kkt_point_are_stalled_and_get_zero_gradients():
    """Altro.jl's tolerances (``ALTROOptions.fast``) stop instances 0 and 1 (mass 1.2) 4 % and more above the cost
    of their KKT points (0.0221408, 0.0263426), at points ALTRO's own tests accept: the KKT certificate reports
    them STALLED, and they get zero gradients with a warning naming them. The default options reach those KKT
    points and are differentiated."""
    optimum = torch.tensor([0.022140766852, 0.026342644443], dtype=F64)
    with pytest.warns(RuntimeWarning,
                      match=r"instance\(s\) \[0, 1\] did not converge \(status \['stalled', 'stalled'\]"):
        sol, leaf, loss = _pendulum_mass_solve([0, 1], tt.ALTROOptions.fast())
    assert sol.status.tolist() == [tt.Status.STALLED, tt.Status.STALLED]
    assert bool((sol.cost.detach() > 1.04 * optimum).all())
    (grad,) = torch.autograd.grad(loss.sum(), [leaf])
    assert grad.tolist() == [0.0, 0.0]
    sol, leaf, loss = _pendulum_mass_solve([0, 1], None)
    assert bool(sol.converged.all())
    torch.testing.assert_close(sol.cost.detach(), optimum, rtol=1e-6, atol=0)
    (grad,) = torch.autograd.grad(loss.sum(), [leaf])
    assert bool((grad != 0).all())


def test_dependent_active_rows_are_counted():
    """LICQ check of the constraint back-propagation: the oscillator's goal equality x_N = goal (two
    rows) with both controls of a two-knot horizon held at their bounds leaves two rows on δx_0 (fixed
    by the initial condition): two dependent rows. With the bounds free there are none."""
    problem = oscillator(u_max=0.5, goal_constraint=True, N=2)
    params = problem.batched_params(1)
    x0 = problem.x0.unsqueeze(0)
    U = torch.full((1, 2, 1), 0.5, dtype=F64)
    X = rollout(problem.dynamics, x0, U, params)
    cons = Constraints(problem)
    upper = cons.ineq_blocks["u_upper"].start
    free = torch.zeros(1, 2, cons.me + cons.mi, dtype=F64)
    held = free.clone()
    held[..., cons.me + upper] = 1.0
    ones = torch.ones(1, cons.meN + cons.miN, dtype=F64)
    assert int(implicit.kkt_system(problem, x0, X, U, params, active=(free, ones)).degenerate.sum()) == 0
    kkt = implicit.kkt_system(problem, x0, X, U, params, active=(held, ones))
    assert bool(kkt.degenerate.all()) and float(implicit.dependent_rows(kkt.factor)[0]) == 2


# ---------------------------------------------------------------- benchmark problems (slow)
TIGHT_ALTRO = ALTROOptions(ilqr=tt.ILQROptions(cost_tolerance=1e-10, gradient_tolerance=1e-6),
                           cost_tolerance=1e-10, cost_tolerance_intermediate=1e-6, constraint_tolerance=1e-8)


@pytest.mark.slow
@pytest.mark.parametrize("name,names", [("pendulum", ["mass", "length", "damping", "gravity"]),
                                        ("car_3obs", ["obstacles", "goal"])])
def test_benchmark_problems_match_central_differences(name, names):
    """Gradients of U.sum() and X[:, -5:].pow(2).sum() with respect to x0 and every model parameter
    (the unicycle has none: the obstacles and the goal instead) against central differences of
    re-solves, warm-started at the nominal solution so that they stay in its basin, to 1e-5 relative."""
    problem = tt.problems.get(name)
    x0 = problem.x0.clone()
    values = {k: problem.params[k].clone() for k in names}

    def solve(x0, values, U0=None):
        x0 = x0.clone().requires_grad_(True)
        leaves = {k: v.clone().requires_grad_(True) for k, v in values.items()}
        sol = tt.solve(problem.with_params(**leaves), x0, method="altro", U0=U0, options=TIGHT_ALTRO)
        assert bool(sol.converged.all()) and sol.max_violation.max() < 1e-10
        return sol, x0, leaves

    sol, x0_leaf, leaves = solve(x0, values)
    U0 = sol.U.detach()
    cons = Constraints(problem)
    g = cons.evaluate(sol.X.detach(), U0, problem.batched_params(1)).ineq
    assert int((g > -1e-8).sum()) >= 1  # inequality constraints are active
    losses = {"U.sum()": lambda s: s.U.sum(), "X[:, -5:]²": lambda s: s.X[:, -5:].pow(2).sum()}
    grads = {label: torch.autograd.grad(loss(sol), [x0_leaf, *leaves.values()], retain_graph=True)
             for label, loss in losses.items()}
    for j, (key, base) in enumerate(zip(["x0", *names], [x0, *values.values()])):
        for i in range(base.numel()):
            h = 1e-6 * (1 + abs(float(base.reshape(-1)[i])))
            out = []
            for sign in (1, -1):
                moved = base.clone()
                moved.reshape(-1)[i] += sign * h
                args = (moved, values) if key == "x0" else (x0, {**values, key: moved})
                resolved = solve(*args, U0=U0)[0]
                out.append({label: float(loss(resolved).detach()) for label, loss in losses.items()})
            for label in losses:
                fd, an = (out[0][label] - out[1][label]) / (2 * h), float(grads[label][j].reshape(-1)[i])
                gmax = max(float(g.abs().max()) for g in grads[label])
                rel = abs(fd - an) / max(abs(fd), abs(an), 1e-2 * gmax)
                assert rel < 1e-5, (label, key, i, fd, an)


@pytest.mark.slow
def test_gradient_benchmark_rows_agree_with_finite_differences():
    """The --grad benchmark's torchtraj row on a small batch: gradients agree with central differences
    of re-solves to 1e-6 and every instance converged."""
    from torchtraj.bench import grad as bench_grad

    lines = []
    rows = bench_grad.run([4], seed=0, method="altro", say=lambda text="": lines.append(text), with_mpc=False)
    ours = next(r for r in rows if r.solver == "torchtraj/altro")
    assert ours.converged == "4/4" and ours.grad_vs_fd < 1e-6, lines
    assert any("linear_box" in line for line in lines)


@pytest.mark.slow
def test_pendulum_gradient_row_checks_instances_whose_re_solves_keep_their_active_set():
    """The --grad benchmark's constrained-pendulum row on four instances of seed 0's B = 256 batch
    (65, 212: their cold re-solves at mass − 1e-6 reached another local solution; 210: holds u_49 at
    its bound with a negative multiplier): the gradient agrees with central differences on the instances
    whose re-solves kept the nominal active set, and the note names the others and the agreement over all."""
    from torchtraj.bench import grad as bench_grad

    x0 = tt.problems.sample_x0("pendulum", 256, 0)[[0, 65, 210, 212]]
    problem = bench_grad.constrained_pendulum()
    row = bench_grad.torchtraj_pendulum(problem, 4, 0, "altro", None, x0=x0)
    assert row["converged"] == "4/4" and row["grad_vs_fd"] < 1e-6, row
    note = row["note"]
    assert note.startswith("FD over ") and "#0" not in note, note  # instance 0 is kept, and a minimum
    if not note.startswith("FD over 4/4"):
        assert "over all 4: " in note and "another active set" in note, note


CUDA_CASES = [(method, dtype) for method in ("altro", "ipm") for dtype in (torch.float64, torch.float32)]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("method,dtype", CUDA_CASES)
def test_cuda_gradients_match_cpu(method, dtype):
    """The car passing its obstacle (an active state inequality) and the pendulum with active control
    bounds, four instances each, solved and differentiated on CUDA: the same statuses and gradients
    with respect to x0 and every parameter as on the CPU (float64 to 1e-7, float32 to 1e-2
    relative: the solves themselves stop at float32's resolution)."""
    float32_options = {"altro": ALTROOptions(constraint_tolerance=1e-4,
                                             projection_options=ProjectionOptions(tolerance=1e-5)),
                       "ipm": None}
    options = float32_options[method] if dtype == torch.float32 else None
    bounded = pendulum(u_lower=torch.tensor([-3.0], dtype=F64), u_upper=torch.tensor([3.0], dtype=F64))
    x0s = {"car10": torch.tensor([[0.0, -0.05, 0.0], [0.0, 0.05, 0.0], [0.0, -0.1, 0.1], [0.0, 0.0, -0.1]]),
           "pendulum10": torch.tensor([[0.1, 0.2], [0.3, -0.1], [-0.2, 0.0], [0.0, 0.4]])}
    for problem in (car(), bounded):
        grads = {}
        for device in ("cpu", "cuda"):
            p = problem.to(dtype=dtype, device=device)
            params = {k: v.clone().requires_grad_(True) for k, v in p.params.items()}
            x0 = x0s[problem.name].to(dtype=dtype, device=device).requires_grad_(True)
            sol = tt.solve(p.with_params(**params), x0, method=method, options=options)
            assert sol.X.device.type == device
            assert bool(sol.converged.all()), (problem.name, device, sol.status.tolist())
            loss = sol.U.sum() + sol.X[:, -5:].pow(2).sum() + sol.cost.sum()
            with warnings.catch_warnings():
                warnings.simplefilter("error", RuntimeWarning)  # no instance left with a zero gradient
                grads[device] = torch.autograd.grad(loss, [x0, *params.values()])
            assert grads[device][0].abs().min() > 0
        rtol = 1e-7 if dtype == torch.float64 else 1e-2
        for name, a, b in zip(["x0", *problem.params], grads["cpu"], grads["cuda"]):
            b = b.cpu()
            assert torch.allclose(a, b, rtol=rtol, atol=rtol * a.abs().max()), (problem.name, name, a, b)


# ------------------------------------------------------------------- the unrolled mode
def _loss_gradients(problem, x0, method, gradients, names):
    params = {k: problem.params[k].clone().requires_grad_(True) for k in names}
    x0 = x0.clone().requires_grad_(True)
    sol = tt.solve(problem.with_params(**params), x0, method=method, gradients=gradients)
    assert bool(sol.converged.all())
    loss = sol.U.sum() + sol.X[:, -5:].pow(2).sum()
    return loss.detach(), torch.autograd.grad(loss, [x0, *params.values()])


def test_unrolled_gradients_are_exact_on_a_linear_quadratic_problem():
    """Linear dynamics and rows, quadratic cost: iLQR's model is the KKT matrix, so differentiating the
    final iLQR step gives the implicit gradient (control bound and velocity bound both active)."""
    problem = oscillator(u_max=0.6, v_max=0.25)
    x0 = torch.tensor([[0.0, 0.0], [0.2, -0.1]], dtype=F64)
    names = ["stiffness", "goal", "w", "v_max"]
    _, exact = _loss_gradients(problem, x0, "altro", "implicit", names)
    _, unrolled = _loss_gradients(problem, x0, "altro", "unrolled", names)
    cons = Constraints(problem)
    sol = tt.solve(problem, x0, method="altro")
    assert int((cons.evaluate(sol.X, sol.U, problem.batched_params(2)).ineq > -1e-9).sum()) >= 2
    for a, b in zip(exact, unrolled):
        assert a.abs().max() > 0
        assert torch.allclose(a, b, rtol=1e-7, atol=1e-7 * a.abs().max())


@pytest.mark.parametrize("method", ["altro", "ipm"])
def test_unrolled_gradients_are_off_where_the_dynamics_are_curved(method):
    """On the pendulum (sin in the dynamics) with an active control bound, the unrolled gradient leaves
    out the dynamics' curvature: central differences of re-solves agree with the implicit gradient to
    1e-6 and differ from the unrolled one by more than 1e-2 (here about 10 %)."""
    problem = pendulum(u_lower=torch.tensor([-3.0], dtype=F64), u_upper=torch.tensor([3.0], dtype=F64))
    x0 = torch.tensor([[0.1, 0.2]], dtype=F64)
    names = ["mass"]
    _, exact = _loss_gradients(problem, x0, method, "implicit", names)
    _, unrolled = _loss_gradients(problem, x0, method, "unrolled", names)
    eps, mass = 1e-6, problem.params["mass"]
    losses = []
    for sign in (1.0, -1.0):  # differentiable solves: their points are refined to the KKT point
        moved = (mass + sign * eps).requires_grad_(True)
        losses.append(float(_loss_gradients(problem.with_params(mass=moved), x0, method, "implicit", [])[0]))
    fd = (losses[0] - losses[1]) / (2 * eps)
    assert abs(fd - float(exact[1])) <= 1e-6 * abs(fd)
    assert abs(fd - float(unrolled[1])) > 1e-2 * abs(fd)


def test_unknown_gradients_mode_is_refused():
    problem = pendulum()
    with pytest.raises(ValueError, match="gradients must be one of"):
        tt.solve(problem, method="ilqr", gradients="backprop")


def test_refinement_of_ipm_solutions_keeps_their_optimum():
    """Interior-point multipliers are positive on every row: a row 1e-3 inside its bound with z ≈ 1e-6
    is inactive (z < s). Held active, refinement moved these linear_box instances of the gradient bench
    1e-3 away, to a dearer point. Refined, they stay within the ipm's own accuracy and get no dearer."""
    from torchtraj.bench import grad as bench_grad

    system = bench_grad.linear_system(0)
    problem = bench_grad.lq_problem(system)
    x0 = bench_grad._instances(256, 0, system)[0][[3, 21, 51, 193, 212, 242, 247]]
    plain = tt.solve(problem, x0, method="ipm")
    A = problem.params["A"].clone().requires_grad_(True)
    refined = tt.solve(problem.with_params(A=A), x0, method="ipm")
    assert bool(plain.converged.all()) and bool(refined.converged.all())
    assert (refined.U.detach() - plain.U).abs().max() < 1e-4
    assert bool((refined.cost.detach() <= plain.cost * (1 + 1e-12)).all())


def test_rows_where_an_ipm_bound_arc_begins_join_the_active_set():
    """Where the control bound of the constrained pendulum begins to bind, an interior-point solution
    leaves rows with z ≈ s ≈ √μ (z = 3e-5, s = 8e-5): neither clearly active nor inactive. Left out,
    the Newton refinement's step violates them; they join the held set, refinement reaches the KKT
    point, and the gradient agrees with central differences of re-solves."""
    from torchtraj.bench import grad as bench_grad

    problem = bench_grad.constrained_pendulum(F64, "cpu")
    x0 = tt.problems.sample_x0("pendulum", 256, 0)[[86, 95]]
    mass = problem.params["mass"]

    def loss_and_grad(m):
        m = m.clone().requires_grad_(True)
        sol = tt.solve(problem.with_params(mass=m.expand(2)), x0, method="ipm")
        loss = sol.U.sum()
        return float(loss.detach()), torch.autograd.grad(loss, m)[0]

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        _, analytic = loss_and_grad(mass)
    eps = 1e-6
    fd = (loss_and_grad(mass + eps)[0] - loss_and_grad(mass - eps)[0]) / (2 * eps)
    assert abs(float(analytic)) > 1.0
    assert abs(fd - float(analytic)) <= 1e-6 * abs(fd)


def test_a_declared_linear_quadratic_problem_gives_the_same_kkt_system():
    """Declared ``linear_quadratic``, the KKT system takes its derivatives at one knot and moves the values and
    gradients from there: the same matrices and Newton right-hand side as the derivatives at every knot, at a
    point that is no solution (defects, rows off their bounds) and with a parameter per instance."""
    from small_problems import oscillator

    g = torch.Generator().manual_seed(3)
    B, N = 4, 15
    X = torch.randn(B, N + 1, 2, generator=g, dtype=F64)
    U = torch.randn(B, N, 1, generator=g, dtype=F64)
    x0 = torch.randn(B, 2, generator=g, dtype=F64)
    params = {"k": torch.tensor([2.0, 1.0, 3.0, 2.5], dtype=F64),
              "goal": torch.tensor([-0.5, 0.0], dtype=F64).repeat(B, 1)}
    systems = [implicit.kkt_system(oscillator(linear_quadratic=declared), x0, X, U, params)
               for declared in (False, True)]
    plain, declared = systems
    for name in ("A", "B", "Q", "R", "S", "QN", "C", "D", "CN", "mask", "maskN"):
        torch.testing.assert_close(getattr(declared.lqr, name), getattr(plain.lqr, name), rtol=1e-12, atol=1e-12)
    for name in ("q", "r", "qN", "c", "x0", "e", "eN"):
        a, b = getattr(declared.newton, name), getattr(plain.newton, name)
        assert float(b.abs().max()) > 1e-2, name  # the point is off its solution in every part
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
