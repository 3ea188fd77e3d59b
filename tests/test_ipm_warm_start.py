"""The interior point's warm start from given duals (``tt.solve(..., duals=...)``, torchtraj/solvers/ipm/warm_start.py)
and the IPM controller's carried duals.

A solve near an earlier one, from its primal-dual point, reaches the same optimum as a cold solve in fewer
iterations; an instance whose barrier is 0 starts as a cold solve does, whatever its batch; the duals are in the
problem's units (the objective's scaling factor of each solve converts them); a control step carries its
multipliers, costates and last barrier to the next, shifted; ``tt.warm_start(solution)`` gives each method's
arguments of such a start."""

import warnings

import pytest
import torch

import torchtraj as tt
from torchtraj import envs, solvers
from torchtraj.core.batch import Batch
from torchtraj.solvers.ipm.scaling import objective_scale

IPM = solvers.get("ipm")


def carried(solution) -> dict:
    return IPM.carried_duals(None, solution, tt.IPOptions())


@pytest.mark.parametrize("name", ["pendulum", "cartpole", "car_3obs"])
def test_a_nearby_solve_from_the_last_primal_dual_point_takes_fewer_iterations_to_the_same_optimum(name):
    problem = tt.problems.get(name)
    first = tt.solve(problem, method="ipm")
    x1 = problem.x0 + 0.01
    cold = tt.solve(problem, x1, method="ipm")
    warm = tt.solve(problem, x1, method="ipm", U0=first.U, X0=first.X, duals=carried(first))
    assert bool(first.converged.all() and cold.converged.all() and warm.converged.all())  # KKT points, certified
    # measured: pendulum 62 -> 21, cart-pole 49 -> 13, car_3obs 130 -> 13
    assert int(warm.iterations[0]) * 2 < int(cold.iterations[0])
    # the same optimum, to the tolerance's resolution of it: the warm cost 1.3e-6 relative below the cold one on
    # the pendulum, whose controls the cost determines only to about 1e-3 (its multipliers are below 5e-4)
    torch.testing.assert_close(warm.cost, cold.cost, rtol=2e-6, atol=0)
    torch.testing.assert_close(warm.U, cold.U, rtol=0, atol=5e-3)


def test_an_instance_whose_barrier_is_zero_starts_cold_whatever_its_batch():
    """The default options take the least-squares multipliers: for the cold instance alone."""
    problem = tt.problems.get("car_3obs")
    first = tt.solve(problem, method="ipm")
    x1 = problem.x0 + torch.tensor([[0.01, 0.0, 0.0], [0.0, 0.02, 0.0]], dtype=torch.float64)
    duals = carried(first)
    both = {"multipliers": {k: v.expand(2, *v.shape[1:]) for k, v in duals["multipliers"].items()},
            "costate": duals["costate"].expand(2, -1, -1),
            "barrier": torch.cat([duals["barrier"], torch.zeros(1, dtype=torch.float64)])}
    U0 = torch.cat([first.U, problem.u_init.unsqueeze(0)])
    mixed = tt.solve(problem, x1, method="ipm", U0=U0, duals=both)
    cold = tt.solve(problem, x1[1:], method="ipm")
    warm = tt.solve(problem, x1[:1], method="ipm", U0=first.U, duals=duals)
    assert int(mixed.iterations[1]) == int(cold.iterations[0]) != int(warm.iterations[0])
    torch.testing.assert_close(mixed.U[1:], cold.U, rtol=0, atol=1e-12)
    torch.testing.assert_close(mixed.U[:1], warm.U, rtol=0, atol=1e-12)
    assert int(mixed.iterations[0]) == int(warm.iterations[0])


def times(problem, factor: float, name: str):
    stage_cost, terminal_cost = problem.stage_cost, problem.terminal_cost
    return problem.replace(stage_cost=lambda x, u, p: factor * stage_cost(x, u, p),
                           terminal_cost=lambda x, p: factor * terminal_cost(x, p), name=name)


def test_the_duals_are_in_the_problems_units():
    """The cart-pole's costs times 8 and times 32: at the warm start (cost gradient 137 and 547) their objective
    factors are ``s_f`` and ``s_f / 4``, which make the same scaled problem to the last bit (powers of two). The
    same warm start, in each problem's units (the second's multipliers, costates and barrier four times the
    first's), then takes the same iterates; the second problem's duals given in the first's units do not."""
    base = tt.problems.get("cartpole")
    eight, thirty_two = times(base, 8.0, "cartpole_times_8"), times(base, 32.0, "cartpole_times_32")
    first = tt.solve(base, method="ipm", options=tt.IPOptions(iterations=8))
    x1 = base.x0 + 0.01
    batch = Batch.build(base, x1, first.U)
    scales = [float(objective_scale(p, first.X, first.U, batch.params, tt.IPOptions())[0]) for p in (eight, thirty_two)]
    assert scales[0] < 1.0 and scales[1] == scales[0] / 4
    duals = dict(carried(first), barrier=torch.tensor([0.01], dtype=torch.float64))  # within the barrier's clamp
    in_units = [{"multipliers": {k: c * v for k, v in duals["multipliers"].items()}, "costate": c * duals["costate"],
                 "barrier": c * duals["barrier"]} for c in (8.0, 32.0)]
    one = tt.solve(eight, x1, method="ipm", U0=first.U, X0=first.X, duals=in_units[0])
    other = tt.solve(thirty_two, x1, method="ipm", U0=first.U, X0=first.X, duals=in_units[1])
    assert bool(one.converged.all()) and one.iterations.tolist() == other.iterations.tolist()
    torch.testing.assert_close(other.U, one.U, rtol=0, atol=1e-12)
    torch.testing.assert_close(other.cost, 4.0 * one.cost, rtol=1e-12, atol=0)
    torch.testing.assert_close(other.history.extra["barrier"], 4.0 * one.history.extra["barrier"], rtol=1e-12, atol=0)
    for name, value in one.multipliers.items():
        torch.testing.assert_close(other.multipliers[name], 4.0 * value, rtol=1e-9, atol=1e-12)
    wrong = tt.solve(thirty_two, x1, method="ipm", U0=first.U, X0=first.X, duals=in_units[0])
    assert wrong.iterations.tolist() != one.iterations.tolist() or (wrong.U - one.U).abs().max() > 1e-9


def test_the_entries_another_method_takes_are_refused_by_name():
    problem = tt.problems.get("pendulum")
    with pytest.raises(ValueError, match=r"duals has unknown entries \['penalties'\]; method 'ipm' takes"):
        tt.solve(problem, method="ipm", duals={"penalties": {}})
    with pytest.raises(ValueError, match=r"duals has unknown entries \['barrier'\]; method 'altro' takes"):
        tt.solve(problem, method="altro", duals={"barrier": torch.ones(1)})
    with pytest.raises(ValueError, match=r"duals\['barrier'\] has shape \(2,\).*\(B,\)"):
        tt.solve(problem, method="ipm", duals={"barrier": torch.ones(2)})
    with pytest.raises(ValueError, match="warm_start_barrier_min must be > 0"):
        tt.solve(problem, method="ipm", options=tt.IPOptions(warm_start_barrier_min=0.0))


def test_a_control_step_carries_its_multipliers_costates_and_last_barrier_shifted():
    env = envs.PendulumEnv()
    mpc = tt.MPC(env.problem(), "ipm", 2)
    states = torch.tensor([[0.3, 2.0], [3.0, 0.2], [0.05, 0.0]], dtype=torch.float64)
    mpc(states)
    first = mpc.solution
    U0, duals = mpc.warm_start()
    assert set(duals) == {"multipliers", "costate", "barrier"}
    for name, value in first.multipliers.items():
        shifted = value[:, 1:] if value.dim() == 3 else value
        torch.testing.assert_close(duals["multipliers"][name][:, :shifted.shape[1]] if value.dim() == 3
                                   else duals["multipliers"][name], shifted, rtol=0, atol=0)
    torch.testing.assert_close(duals["costate"][:, :-1], first.costate[:, 1:], rtol=0, atol=0)
    torch.testing.assert_close(duals["barrier"], first.history.extra["barrier"][:, -1], rtol=0, atol=0)
    assert bool((duals["barrier"] > 0).all()) and duals["costate"].abs().max() > 0
    x1 = first.X[:, 1]
    X0 = torch.cat([x1.unsqueeze(1), first.X[:, 2:], first.X[:, -1:]], 1)
    u = mpc(x1)
    sol = tt.solve(mpc.problem, x1, "ipm", U0=U0, X0=X0, options=mpc.options, duals=duals)
    torch.testing.assert_close(u, sol.U[:, 0].clamp(-3.0, 3.0), rtol=0, atol=1e-12)
    cold = tt.solve(mpc.problem, x1, "ipm", U0=U0, X0=X0, options=mpc.options)
    assert (sol.U - cold.U).abs().max() > 1e-6  # the carried duals change the step
    mpc.reset(torch.tensor([False, True, False]))
    _, after = mpc.warm_start()
    assert float(after["barrier"][1]) == 0.0 and bool((after["barrier"][[0, 2]] > 0).all())


@pytest.mark.parametrize("method", ["ipm", "altro", "ilqr"])
def test_tt_warm_start_gives_what_each_method_takes(method):
    """The interior point: controls, states and duals; ALTRO: controls and multipliers (its X0 would be its
    infeasible start); iLQR: controls alone. The solve from them is the solve from the same arguments by hand."""
    problem = tt.problems.get("pendulum")
    options = {"iterations": 30} if method != "altro" else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # iLQR ignores the pendulum's constraints
        first = tt.solve(problem, method=method, options=options)
        kwargs = tt.warm_start(first)
        expected = {"ipm": {"U0", "X0", "duals"}, "altro": {"U0", "duals"}, "ilqr": {"U0", "duals"}}[method]
        assert set(kwargs) == expected
        assert (kwargs["duals"] is None) == (method == "ilqr")
        if method == "ipm":
            assert set(kwargs["duals"]) == {"multipliers", "costate", "barrier"}
        x1 = problem.x0 + 0.01
        again = tt.solve(problem, x1, method=method, options=options, **kwargs)
        by_hand = tt.solve(problem, x1, method=method, options=options, U0=first.U,
                           X0=first.X if method == "ipm" else None,
                           duals=None if method == "ilqr" else carried(first) if method == "ipm"
                           else {"multipliers": first.multipliers})
    torch.testing.assert_close(again.U, by_hand.U, rtol=0, atol=0)


def test_tt_warm_start_detaches_a_differentiable_solution():
    problem = tt.problems.get("double_integrator")
    x0 = problem.x0.clone().requires_grad_(True)
    first = tt.solve(problem, x0, method="ipm")
    assert first.U.requires_grad
    kwargs = tt.warm_start(first)
    assert not kwargs["U0"].requires_grad and not kwargs["X0"].requires_grad
    assert not any(v.requires_grad for v in kwargs["duals"]["multipliers"].values())
