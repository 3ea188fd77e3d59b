"""Batched torch.func derivatives against central finite differences."""

import pytest
import torch

import torchtraj as tt
from torchtraj.core.constraints import Constraints
from torchtraj.core.derivatives import (
    linearize_dynamics,
    problem_lagrangian_hessian,
    quadratize_cost,
    stage_jacobian,
    terminal_jacobian,
)

EPS = 1e-6


def _random_trajectory(problem, B, seed):
    g = torch.Generator().manual_seed(seed)
    X = problem.x0 + 0.5 * torch.randn(B, problem.N + 1, problem.nx, generator=g, dtype=torch.float64)
    U = problem.u_init + 0.5 * torch.randn(B, problem.N, problem.nu, generator=g, dtype=torch.float64)
    return X, U


def _fd_stage(fn, x, u, p):
    """Central differences of fn(x, u, p) with respect to z = (x, u): (m, nz)."""
    z = torch.cat([x, u])
    nx = x.shape[0]
    cols = []
    for i in range(z.shape[0]):
        e = torch.zeros_like(z)
        e[i] = EPS
        plus, minus = fn((z + e)[:nx], (z + e)[nx:], p), fn((z - e)[:nx], (z - e)[nx:], p)
        cols.append((plus - minus) / (2 * EPS))
    return torch.stack(cols, -1)


@pytest.mark.parametrize("name", ["cartpole", "car_3obs", "quadrotor2d"])
def test_dynamics_and_cost_derivatives_match_finite_differences(name):
    prob = tt.problems.get(name)
    X, U = _random_trajectory(prob, B=2, seed=0)
    P = prob.batched_params(2)
    p = prob.params
    f, A, Bm = linearize_dynamics(prob.dynamics, X, U, P)
    l, lz, lzz, lN, lNx, lNxx = quadratize_cost(prob.stage_cost, prob.terminal_cost, X, U, P)
    for b, k in [(0, 0), (1, prob.N // 2), (1, prob.N - 1)]:
        x, u = X[b, k], U[b, k]
        assert torch.allclose(f[b, k], prob.dynamics(x, u, p), atol=1e-14)
        jac = _fd_stage(prob.dynamics, x, u, p)
        assert torch.allclose(torch.cat([A[b, k], Bm[b, k]], -1), jac, atol=1e-7, rtol=1e-6)
        grad = _fd_stage(lambda x_, u_, p_: prob.stage_cost(x_, u_, p_).reshape(1), x, u, p)[0]
        assert torch.allclose(lz[b, k], grad, atol=1e-7, rtol=1e-6)
        hess = _fd_stage(lambda x_, u_, p_: torch.func.jacrev(
            lambda z: prob.stage_cost(z[:prob.nx], z[prob.nx:], p_))(torch.cat([x_, u_])), x, u, p)
        assert torch.allclose(lzz[b, k], hess, atol=1e-6, rtol=1e-6)
    xN = X[1, -1]
    gN = _fd_stage(lambda x_, u_, p_: prob.terminal_cost(x_, p_).reshape(1), xN, xN.new_zeros(0), p)[0]
    assert torch.allclose(lNx[1], gN, atol=1e-7, rtol=1e-6)


def test_constraint_jacobians_match_finite_differences():
    prob = tt.problems.get("car_3obs")
    cons = Constraints(prob)
    X, U = _random_trajectory(prob, B=2, seed=1)
    P = prob.batched_params(2)
    c, cz = stage_jacobian(cons.stage_ineq, X, U, P)
    assert c.shape == (2, prob.N, cons.mi) and cz.shape == (2, prob.N, cons.mi, prob.nx + prob.nu)
    x, u = X[1, 7], U[1, 7]
    assert torch.allclose(cz[1, 7], _fd_stage(cons.stage_ineq, x, u, prob.params), atol=1e-7, rtol=1e-6)
    cN, cNx = terminal_jacobian(cons.terminal_eq, X[:, -1], P)
    fd = _fd_stage(lambda x_, u_, p_: cons.terminal_eq(x_, p_), X[0, -1], X.new_zeros(0), prob.params)
    assert torch.allclose(cNx[0], fd, atol=1e-7)


def test_lagrangian_hessian_matches_finite_differences():
    prob = tt.problems.get("car_3obs")
    cons = Constraints(prob)
    B, N = 2, prob.N
    X, U = _random_trajectory(prob, B=B, seed=2)
    P = prob.batched_params(B)
    g = torch.Generator().manual_seed(3)
    lam = torch.randn(B, N + 1, prob.nx, generator=g, dtype=torch.float64)
    mu = torch.rand(B, N, cons.mi, generator=g, dtype=torch.float64)
    nuN = torch.randn(B, cons.meN, generator=g, dtype=torch.float64)
    H, HN = problem_lagrangian_hessian(prob, cons, X, U, P, lam, mu=mu, nuN=nuN)
    b, k = 1, 11
    p = prob.params
    nx = prob.nx

    def grad_L(x, u, p_):
        def L(z):
            xx, uu = z[:nx], z[nx:]
            return (prob.stage_cost(xx, uu, p_) + (lam[b, k + 1] * prob.dynamics(xx, uu, p_)).sum()
                    + (mu[b, k] * cons.ineq_knot_mask[k] * cons.stage_ineq(xx, uu, p_)).sum())
        return torch.func.grad(L)(torch.cat([x, u]))

    fd = _fd_stage(grad_L, X[b, k], U[b, k], p)
    assert torch.allclose(H[b, k], fd, atol=1e-6, rtol=1e-6)
    assert torch.allclose(HN[0],
                          torch.zeros_like(HN[0]) + torch.func.hessian(lambda x: prob.terminal_cost(x, p))(X[0, -1]),
                          atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_derivatives_keep_dtype_and_batch_shapes(dtype):
    prob = tt.problems.get("pendulum").to(dtype)
    X, U = _random_trajectory(prob.to(torch.float64), B=3, seed=4)
    X, U = X.to(dtype), U.to(dtype)
    f, A, Bm = linearize_dynamics(prob.dynamics, X, U, prob.batched_params(3))
    assert A.dtype == dtype and A.shape == (3, prob.N, 2, 2) and Bm.shape == (3, prob.N, 2, 1)


def test_derivatives_of_affine_and_quadratic_functions_at_one_stage_are_every_stages():
    """A linear-quadratic problem's functions differentiated at each instance's first stage: the broadcast Jacobians
    and Hessians, the values and the moved gradients are those taken at every stage (a parameter per instance)."""
    from torchtraj.core.derivatives import affine_stage_jacobian, quadratic_stage_hessian, stage_hessian, stage_jacobian

    g = torch.Generator().manual_seed(1)
    B, N, nx, nu = 3, 7, 3, 2
    X = torch.randn(B, N, nx, generator=g, dtype=torch.float64)
    U = torch.randn(B, N, nu, generator=g, dtype=torch.float64)
    params = {"M": torch.randn(B, 4, nx + nu, generator=g, dtype=torch.float64),
              "c": torch.randn(B, 4, generator=g, dtype=torch.float64)}

    def affine(x, u, p):
        return p["M"] @ torch.cat([x, u]) + p["c"]

    def quadratic(x, u, p):
        r = affine(x, u, p)
        return 0.5 * (r @ r) + r.sum()

    for once, every in ((affine_stage_jacobian(affine, X, U, params), stage_jacobian(affine, X, U, params)),
                        (quadratic_stage_hessian(quadratic, X, U, params), stage_hessian(quadratic, X, U, params))):
        for a, b in zip(once, every):
            assert a.shape == b.shape and float(b.abs().max()) > 1e-1
            torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("route", ["one pass at few points", "own pullbacks at many points"])
@pytest.mark.parametrize("name", ["car_3obs", "parallel_park", "car_3obs with stage equalities"])
def test_one_pass_kkt_expansion_matches_the_separate_derivatives(name, route, monkeypatch):
    """The one-pass expansion (cost, Lagrangian gradient and Hessian, dynamics and rows with their Jacobians) is the
    separate passes' (each checked against finite differences above), with every multiplier block nonzero, by
    either route: the rows' Jacobians out of the Hessian's pass (few points: fewer calls) or by their own
    pullbacks (many points: less arithmetic)."""
    from torchtraj.bench.ops import OperatorCounter
    from torchtraj.core import one_pass
    from torchtraj.core.derivatives import problem_lagrangian_expansion
    from torchtraj.core.one_pass import problem_kkt_expansion
    from torchtraj.kkt.model import total_cost

    if route.startswith("own"):
        monkeypatch.setattr(one_pass, "HESSIAN_PASS_POINTS", 0)

    prob = tt.problems.get(name.split()[0])
    if name.endswith("equalities"):
        prob = prob.replace(stage_eq=lambda x, u, p: torch.stack([x[0] * u[0] - 0.1, torch.sin(x[1] * u[1])]))
    cons = Constraints(prob)
    B, N = 2, prob.N
    X, U = _random_trajectory(prob, B=B, seed=5)
    P = prob.batched_params(B)
    g = torch.Generator().manual_seed(6)

    def rand(*shape):
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    lam, nu, mu = rand(B, N + 1, prob.nx), rand(B, N, cons.me), rand(B, N, cons.mi).abs()
    nuN, muN = rand(B, cons.meN), rand(B, cons.miN).abs()
    with OperatorCounter() as calls:
        e = problem_kkt_expansion(prob, cons, X, U, P, lam, nu, mu, nuN, muN)
    monkeypatch.setattr(one_pass, "HESSIAN_PASS_POINTS", 0 if route.startswith("one") else 10 ** 9)
    with OperatorCounter() as other_calls:
        problem_kkt_expansion(prob, cons, X, U, P, lam, nu, mu, nuN, muN)
    assert (calls.total < other_calls.total) == route.startswith("one")
    ref = problem_lagrangian_expansion(prob, cons, X, U, P, lam, nu, mu, nuN, muN)
    f, fz = stage_jacobian(prob.dynamics, X[:, :-1], U, P)
    pairs = [(e.Lz, ref.gradient), (e.Lzz, ref.hessian), (e.LNx, ref.terminal_gradient),
             (e.LNxx, ref.terminal_hessian), (e.f, f), (e.fz, fz), (e.cost, total_cost(prob, X, U, P))]
    for fn, value, jac, m in [(cons.stage_eq, e.h, e.Hz, cons.me), (cons.stage_ineq, e.g, e.Gz, cons.mi)]:
        ref_value, ref_jac = stage_jacobian(fn, X[:, :-1], U, P) if m else (value, jac)
        pairs += [(value, ref_value), (jac, ref_jac)]
    for fn, value, jac, m in [(cons.terminal_eq, e.hN, e.HN, cons.meN), (cons.terminal_ineq, e.gN, e.GN, cons.miN)]:
        ref_value, ref_jac = terminal_jacobian(fn, X[:, -1], P) if m else (value, jac)
        pairs += [(value, ref_value), (jac, ref_jac)]
    assert cons.mi + cons.meN > 0 and (cons.me > 0) == name.endswith("equalities")
    for got, want in pairs:
        assert got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_one_pass_cost_expansion_and_values_match_the_separate_passes():
    """Without multipliers the one-pass expansion is the cost's (a Gauss-Newton model's) with the rows' Jacobians;
    the values-only pass, at a line search's stacked trial points ``(B, L, ...)``, is the separate evaluations'."""
    from torchtraj.core.batching import map_stage, map_state
    from torchtraj.core.one_pass import problem_kkt_expansion, problem_values
    from torchtraj.kkt.model import total_cost

    prob = tt.problems.get("car_3obs")
    cons = Constraints(prob)
    X, U = _random_trajectory(prob, B=2, seed=7)
    P = prob.batched_params(2)
    e = problem_kkt_expansion(prob, cons, X, U, P)
    cost = quadratize_cost(prob.stage_cost, prob.terminal_cost, X, U, P)
    f, fz = stage_jacobian(prob.dynamics, X[:, :-1], U, P)
    g, Gz = stage_jacobian(cons.stage_ineq, X[:, :-1], U, P)
    hN, HN = terminal_jacobian(cons.terminal_eq, X[:, -1], P)
    for got, want in [(e.Lz, cost.gradient), (e.Lzz, cost.hessian), (e.LNx, cost.terminal_gradient),
                      (e.LNxx, cost.terminal_hessian), (e.f, f), (e.fz, fz), (e.g, g), (e.Gz, Gz), (e.hN, hN),
                      (e.HN, HN), (e.cost, total_cost(prob, X, U, P))]:
        torch.testing.assert_close(got, want, rtol=0, atol=0)
    with pytest.raises(ValueError, match="costate"):
        problem_kkt_expansion(prob, cons, X, U, P, nuN=torch.zeros(2, cons.meN, dtype=torch.float64))
    Xc = torch.stack([X, X + 0.1, X - 0.2], 1)
    Uc = torch.stack([U, U * 0.5, U + 0.3], 1)
    v = problem_values(prob, cons, Xc, Uc, P)
    for got, want in [(v.cost, total_cost(prob, Xc, Uc, P)), (v.f, map_stage(prob.dynamics, Xc[..., :-1, :], Uc, P)),
                      (v.g, map_stage(cons.stage_ineq, Xc[..., :-1, :], Uc, P)),
                      (v.hN, map_state(cons.terminal_eq, Xc[..., -1, :], P))]:
        assert got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=1e-13, atol=1e-13)
    assert v.h.shape == (2, 3, prob.N, 0) and v.gN.shape == (2, 3, 0)


def test_altro_expansion_from_one_pass_is_the_separate_passes():
    """ALTRO's model of ``L_A`` (eqs. 5-12) takes the cost's Hessian and the dynamics' and rows' Jacobians from the
    one-pass expansion, the rows stacked as ``stage_fn`` stacks them (inequalities, then equalities; a state row
    off at knot 0): the same model, bit for bit, as the cost's separate passes and the rows' own Jacobians."""
    from small_problems import oscillator

    from torchtraj.kkt.model import cost_model
    from torchtraj.solvers.altro.augmented_lagrangian import AugmentedLagrangian, Duals

    prob = oscillator(stage_eq=lambda x, u, p: (x[0] * u[0] - 0.1).reshape(1),
                      terminal_ineq=lambda x, p: (x[0] * x[0] - 1.0).reshape(1))
    cons = Constraints(prob)
    X, U = _random_trajectory(prob, B=3, seed=11)
    P = prob.batched_params(3)
    g = torch.Generator().manual_seed(12)
    empty = Duals.initial(cons, 3, 10.0, X[:, 0])
    duals = Duals(torch.rand(empty.stage.shape, generator=g, dtype=torch.float64),
                  torch.rand(empty.terminal.shape, generator=g, dtype=torch.float64),
                  empty.stage_penalty, empty.terminal_penalty)
    al = AugmentedLagrangian(cons, duals)
    lqr, rhs = al.expand(X, U, P)
    want, want_rhs = cost_model(prob, X, U, P)
    c, Cz, cN, CN = al.row_jacobians(X, U, P)
    assert c.shape[-1] == cons.mi + cons.me == 4 and cN.shape[-1] == 2
    c, Cz = c * al.knot_mask, Cz * al.knot_mask.unsqueeze(-1)
    w = al._weights(c, duals.stage, duals.stage_penalty, al.is_ineq) * al.knot_mask
    H = Cz.mT @ (w.unsqueeze(-1) * Cz)
    grad = (Cz.mT @ (duals.stage + w * c).unsqueeze(-1)).squeeze(-1)
    wN = al._weights(cN, duals.terminal, duals.terminal_penalty, al.is_ineqN)
    nx = prob.nx
    for got, expected in [(lqr.A, want.A), (lqr.B, want.B), (lqr.Q, want.Q + H[..., :nx, :nx]),
                          (lqr.R, want.R + H[..., nx:, nx:]), (lqr.S, want.S + H[..., nx:, :nx]),
                          (lqr.QN, want.QN + CN.mT @ (wN.unsqueeze(-1) * CN)),
                          (rhs.q, want_rhs.q + grad[..., :nx]), (rhs.r, want_rhs.r + grad[..., nx:]),
                          (rhs.qN, want_rhs.qN + (CN.mT @ (duals.terminal + wN * cN).unsqueeze(-1)).squeeze(-1))]:
        torch.testing.assert_close(got, expected, rtol=0, atol=0)


def test_one_pass_of_a_points_values_gives_the_rows_and_violation_of_the_separate_passes():
    """ALTRO's and HM-iLQR's merits, measures and violations read one ``problem_values`` pass without the dynamics
    (``AugmentedLagrangian.point``): its rows stacked as ``stage_fn`` stacks them are the rows' own ``vmap``s at a
    line search's candidates, and ``Constraints.max_violation_of`` its values is ``max_violation``, bit for bit."""
    from small_problems import oscillator

    from torchtraj.core.one_pass import problem_values
    from torchtraj.solvers.altro.augmented_lagrangian import AugmentedLagrangian, Duals

    prob = oscillator(stage_eq=lambda x, u, p: (x[0] * u[0] - 0.1).reshape(1),
                      terminal_ineq=lambda x, p: (x[0] * x[0] - 1.0).reshape(1))
    for problem in (prob, tt.problems.get("car_3obs")):
        cons = Constraints(problem)
        X, U = _random_trajectory(problem, B=2, seed=3)
        P = problem.batched_params(2)
        al = AugmentedLagrangian(cons, Duals.initial(cons, 2, 10.0, X[:, 0]))
        Xc, Uc = torch.stack([X, X + 0.1, X - 0.2], 1), torch.stack([U, U * 0.5, U + 0.3], 1)
        point = al.point(Xc, Uc, P)
        assert point.f.shape == (2, 3, problem.N, 0)
        for got, want in zip(al.row_values(Xc, Uc, P, point), al.row_values(Xc, Uc, P)):
            assert got.shape == want.shape and torch.equal(got, want)
        v = problem_values(problem, cons, X, U, P, dynamics=False)
        assert torch.equal(cons.max_violation_of(v.h, v.g, v.hN, v.gN), cons.max_violation(X, U, P))


def test_a_stage_mapper_evaluates_as_map_stage_with_shared_and_batched_parameters():
    """``stage_mapper(fn, params)`` (a rollout's steps: the parameters split once) gives ``map_stage``'s values to the
    last bit, for parameters shared by the batch (expanded) and per instance, with and without extra dimensions."""
    from torchtraj.core.batching import map_stage, stage_mapper

    g = torch.Generator().manual_seed(3)
    fn = tt.rk4(lambda x, u, p: torch.stack([x[1], (u[0] - p["k"] * torch.sin(x[0])) / p["m"]]), 0.1)
    shared, mass = (torch.tensor([v], dtype=torch.float64).expand(3) for v in (2.0, 0.5))
    batched = torch.rand(3, generator=g, dtype=torch.float64) + 1
    for params in ({"k": shared, "m": mass}, {"k": batched, "m": mass}, {"k": batched, "m": batched}):
        step = stage_mapper(fn, params)
        for lead in ((3,), (3, 4)):
            X = torch.randn(*lead, 2, generator=g, dtype=torch.float64)
            U = torch.randn(*lead, 1, generator=g, dtype=torch.float64)
            assert torch.equal(step(X, U), map_stage(fn, X, U, params))
