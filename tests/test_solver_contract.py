"""The contract every registered method keeps (torchtraj.solvers): one test matrix over the registry.

For each method of ``torchtraj.solvers.names()`` and each of a few small problems: it converges, to a KKT point of
the problem it declares it solves (the constrained one where it ``handles_constraints``, else the unconstrained
one, or the one its ``kkt_problem`` names), a failing instance changes no other, a batch is its instances solved alone,
float32 stays float32, and the arguments it does not declare (``X0``, ``duals``) are refused by name. Then ``tt.MPC``
swings the pendulum up with every method that handles constraints. A new method is covered by registering it; nothing
here names one, except the tight options chosen by options class (a new class gets its defaults).
"""

import dataclasses
import warnings

import pytest
import torch
from kkt import kkt_residuals

import torchtraj as tt
import torchtraj.kkt
from torchtraj import envs, problems, solvers
from torchtraj.core.constraints import Constraints, stack_blocks
from torchtraj.core.derivatives import stage_jacobian

F64 = torch.float64
METHODS = solvers.names()
CONSTRAINED = [m for m in METHODS if solvers.get(m).handles_constraints]


def small(name: str, dtype=F64) -> tt.Problem:
    """The contract's problems, short enough for every method: the double integrator as in the problem set (N = 20,
    linear-quadratic, control and state bounds, a terminal goal), and the pendulum over N = 10 from hanging towards
    upright without its terminal goal (nonlinear; the torque bound is active at the start), constrained or not."""
    if name == "double_integrator":
        return problems.get(name, dtype=dtype)
    problem = problems.get(name, dtype=dtype)
    return problem.replace(horizon=10, u_init=torch.zeros(1, dtype=dtype), terminal_eq=None)


PROBLEMS = ["double_integrator", "pendulum", "pendulum_unconstrained"]


def tight(method: str, name: str):
    """Options that take each method to its KKT point to round-off (the problem set's for ALTRO's options class)."""
    solver = solvers.get(method)
    if solver.options_class is tt.ALTROOptions:
        return problems.altro_options(name)
    if solver.options_class is tt.ILQROptions:
        return tt.ILQROptions(cost_tolerance=1e-14, gradient_tolerance=1e-9)
    if solver.options_class is tt.HMILQROptions:  # the paper's ε_v = 1e-3 stops short of a KKT point to 1e-5
        return tt.HMILQROptions(cost_tolerance=1e-12, iterations=300)
    return solver.default_options()


def x0s(name: str, count: int, dtype=F64) -> torch.Tensor:
    """``count`` feasible initial states of seed 0 (the double integrator's second one cannot reach its goal in
    time: IPOPT finds it infeasible)."""
    rows = [0, 2, 3] if name == "double_integrator" else [0, 1, 2]
    return problems.sample_x0(name, 4, seed=0)[rows[:count]].to(dtype)


def solve(method, name, x0, dtype=F64, **kwargs):
    """``tt.solve`` of ``small(name)``; the warning of a method that ignores the constraints is expected."""
    problem = small(name, dtype)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*ignores the constraints")
        return problem, tt.solve(problem, x0, method, options=tight(method, name), **kwargs)


def unconstrained(problem: tt.Problem) -> tt.Problem:
    """``problem`` without its constraints: the problem a method that ignores them solves."""
    return problem.replace(u_lower=None, u_upper=None, x_lower=None, x_upper=None, stage_eq=None, stage_ineq=None,
                           state_ineq=None, terminal_eq=None, terminal_ineq=None)


def with_costate(problem: tt.Problem, sol: tt.Solution) -> tt.Solution:
    """``sol`` with, where the method returns none (AL-iLQR skips the projection that computes them), the costates
    that make the Lagrangian stationary in the states: ``λ_N = ∂L₀/∂x_N``, ``λ_k = ∂L₀/∂x_k + A_kᵀ λ_{k+1}``,
    ``L₀`` the cost plus the multipliers' constraint terms and ``A_k = ∂f/∂x``. The check is then stationarity
    in U."""
    if sol.costate is not None:
        return sol
    c, B, nx = Constraints(problem), sol.X.shape[0], problem.nx
    params = problem.batched_params(B)
    X = sol.X.detach().clone().requires_grad_(True)
    values = c.evaluate(X, sol.U, params)
    stage, terminal = stack_blocks(c, sol.multipliers, 0.0, X)
    ineq = torch.where(c.ineq_knot_mask > 0, values.ineq, torch.zeros_like(values.ineq))
    L = (tt.kkt.total_cost(problem, X, sol.U, params).sum() + (stage[..., :c.mi] * ineq).sum()
         + (stage[..., c.mi:] * values.eq).sum() + (terminal[:, :c.miN] * values.ineqN).sum()
         + (terminal[:, c.miN:] * values.eqN).sum())
    (gx,) = torch.autograd.grad(L, X)
    A = stage_jacobian(problem.dynamics, sol.X[:, :-1], sol.U, params)[1][..., :nx]
    lam = [gx[:, -1]]
    for k in range(problem.N - 1, -1, -1):
        lam.append(gx[:, k] + (A[:, k].transpose(-1, -2) @ lam[-1].unsqueeze(-1)).squeeze(-1))
    return dataclasses.replace(sol, costate=torch.stack(lam[::-1], 1))


# ---------------------------------------------------------------------------------------------- declarations
def test_the_registry_lists_solvers_that_declare_themselves():
    assert METHODS and len(set(METHODS)) == len(METHODS)
    for name in METHODS:
        solver = solvers.get(name)
        assert isinstance(solver, tt.Solver) and solver.name == name
        assert isinstance(solver.default_options(), solver.options_class)
        for flag in ("handles_constraints", "takes_state_guess", "takes_duals", "kkt_point"):
            assert isinstance(getattr(solver, flag), bool), (name, flag)
        assert solvers.get(tt.Method(name)) is solver  # the enum is the registry's names
    assert [m.value for m in tt.Method] == METHODS
    with pytest.raises(ValueError, match="unknown method 'newton'; choose one of") as info:
        solvers.get("newton")
    assert all(repr(name) in str(info.value) for name in METHODS)
    with pytest.raises(ValueError, match="already registered"):
        solvers.register(solvers.get(METHODS[0]))


# ---------------------------------------------------------------------------------------------- converged KKT points
@pytest.mark.parametrize("name", PROBLEMS)
@pytest.mark.parametrize("method", METHODS)
def test_converges_to_a_kkt_point_of_what_it_solves(method, name):
    solver = solvers.get(method)
    problem, sol = solve(method, name, x0s(name, 2))
    assert sol.method == method and sol.status.shape == (2,)
    assert (sol.status == tt.Status.CONVERGED).all(), sol.status
    if not solver.kkt_point:
        return
    declared = solver.kkt_problem(problem, tight(method, name))
    if declared is not None:  # the KKT point of the problem it declares instead (eILQR: inequalities as barriers)
        violation = torchtraj.kkt.largest_violation(declared, sol.X, sol.U, declared.batched_params(2))
        assert float(violation.max()) < 1e-6
        stationarity, _, _ = kkt_residuals(declared, with_costate(declared, sol))
    elif solver.handles_constraints:
        assert float(sol.max_violation.max()) < 1e-6
        stationarity, dual_min, complementarity = kkt_residuals(problem, with_costate(problem, sol))
        assert dual_min > -1e-8, dual_min  # inequality multipliers are nonnegative
        assert complementarity < 1e-6, complementarity
        if problem.has_constraints:  # not vacuous: some inequality is active, with a multiplier away from zero
            assert max(float(v.abs().max()) for k, v in sol.multipliers.items() if k != "terminal_eq") > 1e-3
    else:  # the unconstrained KKT point, also of a constrained problem (the implicit layer's constrained=False)
        stationarity, _, _ = kkt_residuals(unconstrained(problem), sol)
    assert stationarity < 1e-5, stationarity


@pytest.mark.parametrize("method", METHODS)
def test_a_method_that_ignores_constraints_says_so(method):
    problem = small("pendulum")
    options = tt.solvers.get(method).step_options(None, 2)  # two iterations: the warning is the point
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tt.solve(problem, method=method, options=options)
    said = any("ignores the constraints" in str(w.message) for w in caught)
    assert said is not solvers.get(method).handles_constraints


# ---------------------------------------------------------------------------------------------- batches
@pytest.mark.parametrize("method", METHODS)
def test_a_nan_instance_fails_alone_and_changes_no_other(method):
    name = "pendulum"
    good = x0s(name, 2)
    bad = torch.stack([good[0], torch.full_like(good[0], float("nan")), good[1]])
    _, with_nan = solve(method, name, bad)
    _, without = solve(method, name, good)
    assert with_nan.status[1] not in (tt.Status.CONVERGED, tt.Status.RUNNING), with_nan.status
    keep = torch.tensor([0, 2])
    assert torch.equal(with_nan.status[keep], without.status)
    assert torch.equal(with_nan.iterations[keep], without.iterations)
    for field in ("X", "U", "cost"):  # bit for bit
        assert torch.equal(getattr(with_nan, field)[keep], getattr(without, field)), field


@pytest.mark.parametrize("method", METHODS)
def test_a_batch_is_its_instances_solved_alone(method):
    name = "pendulum"
    x0 = x0s(name, 2)
    _, batch = solve(method, name, x0)
    for i in range(2):
        _, alone = solve(method, name, x0[i])
        assert int(alone.status[0]) == int(batch.status[i])
        torch.testing.assert_close(alone.U[0], batch.U[i], rtol=0, atol=1e-9)
        torch.testing.assert_close(alone.cost[0], batch.cost[i], rtol=1e-10, atol=0)


@pytest.mark.parametrize("method", METHODS)
def test_float32_runs_in_float32_with_a_status_per_instance(method):
    # Convergence in float32 is not part of the contract today: with these options every method converges on this
    # problem here, but with its defaults ALTRO stops at MAX_ITERATIONS (its projection's tolerance of 1e-8 is below
    # float32's resolution of the constraints). What must hold: the dtype is kept, every instance ends with a final
    # status, a NaN instance fails alone, and an instance that converged is at the float64 solution to float32's
    # accuracy.
    name = "pendulum"
    x0 = x0s(name, 3)
    x0[1] = float("nan")
    _, sol = solve(method, name, x0.float(), dtype=torch.float32)
    assert sol.X.dtype == sol.U.dtype == sol.cost.dtype == torch.float32
    assert sol.status.shape == (3,) and not (sol.status == tt.Status.RUNNING).any()
    assert sol.status[1] != tt.Status.CONVERGED
    assert torch.isfinite(sol.U[[0, 2]]).all() and torch.isfinite(sol.cost[[0, 2]]).all()
    _, ref = solve(method, name, x0[[0, 2]])
    for i, j in ((0, 0), (2, 1)):
        if sol.status[i] == tt.Status.CONVERGED:
            # the cost is what float32 resolves (measured: within 4e-7 relative, eight seeds); the controls are
            # determined only to about 5e-3 on this problem's flattest directions, where a change of the
            # controls moves the cost by less than float32's resolution of it (measured up to 4.2e-3)
            torch.testing.assert_close(sol.cost[i].double(), ref.cost[j], rtol=1e-6, atol=0)
            torch.testing.assert_close(sol.U[i].double(), ref.U[j], rtol=0, atol=5e-3)


# ---------------------------------------------------------------------------------------------- refused arguments
@pytest.mark.parametrize("method", METHODS)
def test_undeclared_arguments_are_refused_by_name(method):
    solver = solvers.get(method)
    problem = small("double_integrator")
    X0 = torch.zeros(problem.N + 1, problem.nx, dtype=F64)
    if not solver.takes_state_guess:
        with pytest.raises(ValueError, match=f"method '{method}'.*cannot take X0"):
            tt.solve(problem, method=method, X0=X0)
    assert bool(solver.dual_entries) == solver.takes_duals  # a method that takes duals says which
    if not solver.takes_duals:
        with pytest.raises(ValueError, match=f"method '{method}' takes no warm-started duals"):
            tt.solve(problem, method=method, duals={"multipliers": {}})
    else:
        unknown = next(e for e in ("multipliers", "penalties", "costate", "barrier") if e not in solver.dual_entries)
        with pytest.raises(ValueError, match=rf"duals has unknown entries \['{unknown}'\]; method '{method}' takes"):
            tt.solve(problem, method=method, duals={unknown: {}})
    with pytest.raises(TypeError, match=f"options for method '{method}' must be {solver.options_class.__name__}"):
        tt.solve(problem, method=method, options=3)


# ---------------------------------------------------------------------------------------------- closed loop
#: the closed loop of the methods MPC is mostly run with in the default run; the others' under -m slow
MPC_DEFAULT_RUN = ("altro", "ipm")


@pytest.mark.parametrize("method", [m if m in MPC_DEFAULT_RUN else pytest.param(m, marks=pytest.mark.slow)
                                    for m in CONSTRAINED])
def test_mpc_swings_the_pendulum_up(method):
    """3 iterations per control step, as tests/test_mpc.py; seed 1 (ALTRO upright from step 46 there, the IPM from
    step 41; AL-iLQR as ALTRO, which MPC runs without its projection anyway)."""
    env = envs.PendulumEnv(max_episode_steps=70)
    policy = tt.MPC(env.problem(), method, 3)
    obs, _ = env.reset(seed=1)
    angles = [obs[0]]
    for _ in range(70):
        obs, *_ = env.step(policy(obs))
        angles.append(obs[0])
    error = envs.upright_error(torch.as_tensor(angles)).abs()
    # as tests/test_mpc.py: from hanging to within 0.1 rad of upright over the last 0.75 s (16 steps)
    assert error[0] > 3.0 and (error[-16:] <= 0.1).all(), (method, error[-16:])
