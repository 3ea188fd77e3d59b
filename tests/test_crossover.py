"""The interior-point method's active-set crossover on linear-quadratic problems (torchtraj/crossover.py)."""

from types import SimpleNamespace

import pytest
import torch
from kkt import kkt_residuals
from small_problems import oscillator, pendulum10

import torchtraj as tt

F64 = torch.float64

# the oscillator's instances that have a solution (from [0.9, 0.4] the state row and the terminal row conflict)
OSCILLATOR_X0 = torch.tensor([[0.5, 0.0], [0.8, -0.3], [0.3, 0.2], [0.1, 0.0], [0.4, -0.2]], dtype=F64)


def double_integrator(u_max=1.0, N=20):
    """Position and velocity driven to the origin with ``|u| ≤ u_max``: its only rows are control bounds."""
    dt = 0.1
    A = torch.tensor([[1.0, dt], [0.0, 1.0]], dtype=F64)
    B = torch.tensor([[0.5 * dt * dt], [dt]], dtype=F64)
    return tt.Problem(
        dynamics=lambda x, u, p: p["A"] @ x + p["B"] @ u,
        stage_cost=lambda x, u, p: 0.5 * (x @ x) + 0.05 * (u @ u),
        terminal_cost=lambda x, p: 5.0 * (x @ x),
        x0=torch.zeros(2, dtype=F64), horizon=N, nu=1, params={"A": A, "B": B},
        u_lower=torch.tensor([-u_max], dtype=F64), u_upper=torch.tensor([u_max], dtype=F64),
        linear_quadratic=True, name="double_integrator")


def _starts(batch=12, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(batch, 2, generator=g, dtype=F64)


def test_crossover_lands_on_the_kkt_point_of_the_active_set():
    """With a state row on an arc, control bounds and a terminal equality (the general rows of the Riccati core):
    the crossover's solutions are KKT points to round-off, where the interior-point iterate it started from is one
    to its tolerance, and they are the optimum the interior-point method approaches at a tighter tolerance."""
    problem = oscillator(linear_quadratic=True)
    plain = tt.solve(problem, OSCILLATOR_X0, method="ipm", options=tt.IPOptions(crossover=False))
    tight = tt.solve(problem, OSCILLATOR_X0, method="ipm", options=tt.IPOptions(crossover=False, tolerance=1e-12))
    crossed = tt.solve(problem, OSCILLATOR_X0, method="ipm")
    for sol in (plain, tight, crossed):
        assert bool(sol.converged.all()), sol.status
    X, U = crossed.X, crossed.U
    assert bool(((X[:, 1:-1, 0] < -0.2 + 1e-9).sum(-1) >= 1).all())  # the state row holds on an arc
    assert bool(((U.abs() > 0.6 - 1e-9).flatten(1).sum(-1) >= 1).any())  # a bound holds
    assert bool(((X[:, 1:-1, 0] > -0.2 + 1e-2).sum(-1) >= 1).all())  # and rows are off elsewhere
    stationarity, most_negative, complementarity = kkt_residuals(problem, crossed)
    assert stationarity < 1e-13 and most_negative >= 0.0 and complementarity < 1e-13
    plain_stationarity, _, plain_complementarity = kkt_residuals(problem, plain)
    assert plain_stationarity > 1e-12 or plain_complementarity > 1e-10  # the test can tell the two apart
    assert torch.allclose(crossed.cost, tight.cost, rtol=1e-11, atol=0)
    assert float(crossed.max_violation.max()) < 1e-13


def test_the_active_set_start_settles_box_constrained_instances():
    """Control bounds alone: the primal-dual active-set rounds from the unconstrained optimum settle every instance
    before the first interior-point iteration, at the optimum of the interior-point method at a tight tolerance."""
    problem = double_integrator()
    x0 = _starts()
    tight = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(crossover=False, tolerance=1e-12))
    sol = tt.solve(problem, x0, method="ipm")
    assert bool(sol.converged.all()) and bool(tight.converged.all())
    saturated = (sol.U.abs() > 1.0 - 1e-9).flatten(1).any(-1)
    assert bool(saturated.any()) and not bool(saturated.all())  # bounds active on some instances, not on all
    assert int(sol.iterations.max()) <= tt.IPOptions().crossover_start_rounds
    assert int(tight.iterations.min()) > int(sol.iterations.max())
    assert float((sol.U - tight.U).abs().max()) < 1e-9
    stationarity, most_negative, complementarity = kkt_residuals(problem, sol)
    assert stationarity < 1e-13 and most_negative >= 0.0 and complementarity < 1e-13
    # the gains are those of the held system: the first control's derivative in x0 with the active set held
    leaf = x0.clone().requires_grad_(True)
    first = tt.solve(problem, leaf, method="ipm").U[:, 0, 0]
    (du0_dx0,) = torch.autograd.grad(first.sum(), leaf)
    assert float(du0_dx0.abs().max()) > 1e-2
    torch.testing.assert_close(sol.K[:, 0, 0], du0_dx0, rtol=1e-9, atol=1e-12)


def test_instances_the_start_does_not_settle_go_on_with_the_interior_point_iterations():
    """One round is the unconstrained optimum: instances whose optimum it is end there (one iteration), the others
    iterate and cross over later, to the same optimum."""
    problem = double_integrator()
    x0 = _starts()
    full = tt.solve(problem, x0, method="ipm")
    one = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(crossover_start_rounds=1))
    assert bool(one.converged.all())
    free = ~(full.U.abs() > 1.0 - 1e-9).flatten(1).any(-1)
    assert bool(free.any()) and not bool(free.all())
    assert bool((one.iterations[free] == 1).all()) and bool((one.iterations[~free] > 1).all())
    assert float((one.U - full.U).abs().max()) < 1e-9


def test_the_least_squares_multipliers_are_estimated_for_the_instances_the_start_does_not_settle(monkeypatch):
    """The start's first candidate holds no row and reads no multiplier, so the least-squares estimate of the
    multipliers (W&B §3.6: a factorisation of the batch and an expansion) waits for it: none where every instance
    ends there, the unsettled instances' alone where one round leaves some (they iterate from it as before)."""
    from torchtraj.solvers.ipm import solver as ipm_solver

    calls = []
    estimate = ipm_solver.least_squares_multipliers

    def spy(cons, model, it, running, opts):
        calls.append(running.clone())
        return estimate(cons, model, it, running, opts)

    monkeypatch.setattr(ipm_solver, "least_squares_multipliers", spy)
    problem = double_integrator()
    x0 = _starts()
    full = tt.solve(problem, x0, method="ipm")
    assert bool(full.converged.all()) and calls == []
    one = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(crossover_start_rounds=1))
    free = ~(full.U.abs() > 1.0 - 1e-9).flatten(1).any(-1)
    assert len(calls) == 1 and torch.equal(calls[0], ~free)
    assert bool(one.converged.all()) and float((one.U - full.U).abs().max()) < 1e-9
    # a problem with a state row takes no start: the estimate comes first, for every instance
    calls.clear()
    tt.solve(oscillator(linear_quadratic=True), OSCILLATOR_X0, method="ipm")
    assert len(calls) == 1 and bool(calls[0].all())


def test_a_batch_crosses_over_as_each_instance_alone():
    """The crossover gathers the instances it tries: every instance's answer is its own solve's, with a failing
    instance (a NaN in its state) in the batch."""
    problem = oscillator(linear_quadratic=True)
    x0 = torch.cat([OSCILLATOR_X0, torch.tensor([[float("nan"), 0.0]], dtype=F64)])
    batch = tt.solve(problem, x0, method="ipm")
    assert batch.status[-1] == tt.Status.NON_FINITE and bool(batch.converged[:-1].all())
    for i in range(OSCILLATOR_X0.shape[0]):
        alone = tt.solve(problem, x0[i], method="ipm")
        assert alone.status[0] == batch.status[i] and alone.iterations[0] == batch.iterations[i]
        torch.testing.assert_close(batch.U[i], alone.U[0], rtol=0, atol=1e-12)
        torch.testing.assert_close(batch.X[i], alone.X[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("start_rounds", [8, 1])
def test_the_masked_crossover_of_cuda_graphs_gives_the_gathered_answers(monkeypatch, start_rounds):
    """With CUDA graphs the crossover masks the rows it is done with instead of gathering the others
    (``_cross_over_masked``). Forced here on the CPU, where the graphed kernels run eagerly: with a failing
    instance in the batch, the others reach KKT points to round-off, with the statuses, iteration counts and
    answers of the gathered crossover; with one start round, most instances iterate and cross over later,
    a few at a time."""
    from torchtraj.solvers.ipm import kernels as interior_point

    problem = double_integrator()
    x0 = torch.cat([_starts(), torch.tensor([[float("nan"), 0.0]], dtype=F64)])
    gathered = tt.solve(problem, x0, method="ipm", options=tt.IPOptions(crossover_start_rounds=start_rounds))
    monkeypatch.setattr(interior_point, "graphs_used", lambda options, device: options.cuda_graphs)
    masked = tt.solve(problem, x0, method="ipm",
                      options=tt.IPOptions(crossover_start_rounds=start_rounds, cuda_graphs=True))
    assert masked.status[-1] == tt.Status.NON_FINITE and bool(masked.converged[:-1].all())
    assert torch.equal(masked.status, gathered.status) and torch.equal(masked.iterations, gathered.iterations)
    torch.testing.assert_close(masked.U[:-1], gathered.U[:-1], rtol=0, atol=1e-12)
    torch.testing.assert_close(masked.K[:-1], gathered.K[:-1], rtol=0, atol=1e-12)
    ok = masked.converged
    solved = SimpleNamespace(X=masked.X[ok], U=masked.U[ok], costate=masked.costate[ok],
                             multipliers={k: v[ok] for k, v in masked.multipliers.items()})
    stationarity, most_negative, complementarity = kkt_residuals(problem, solved)
    assert stationarity < 1e-13 and most_negative >= 0.0 and complementarity < 1e-13


def test_a_problem_not_declared_linear_quadratic_is_not_crossed_over():
    """The crossover's single Newton step is exact only for a linear-quadratic problem: others solve as without."""
    problem = pendulum10(u_lower=torch.tensor([-2.0], dtype=F64), u_upper=torch.tensor([2.0], dtype=F64))
    on = tt.solve(problem, method="ipm")
    off = tt.solve(problem, method="ipm", options=tt.IPOptions(crossover=False))
    assert bool(on.converged.all())
    assert torch.equal(on.U, off.U) and torch.equal(on.iterations, off.iterations)


def test_crossover_rounds_are_checked():
    with pytest.raises(ValueError, match="crossover_rounds"):
        tt.IPOptions(crossover_rounds=-1)
    with pytest.raises(ValueError, match="crossover_start_rounds"):
        tt.IPOptions(crossover_start_rounds=-2)
