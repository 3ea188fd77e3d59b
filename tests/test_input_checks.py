"""Bad or careless input is named (issue 23, items 5 and 6): the construction probe, bounds, parameter batches,
horizons, options, warm-started duals, the default method, MPC, logging and the environments."""

import logging
import warnings

import numpy as np
import pytest
import torch

import torchtraj as tt
from torchtraj import solvers

F64 = torch.float64


def make(**changes):
    base = dict(
        dynamics=lambda x, u, p: torch.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * (u[0] - p["k"] * x[0])]),
        stage_cost=lambda x, u, p: 0.5 * (x * x).sum() + 0.5 * (u * u).sum(),
        terminal_cost=lambda x, p: 10.0 * (x * x).sum(),
        x0=torch.tensor([1.0, 0.5], dtype=F64),
        horizon=10,
        nu=1,
        params={"k": torch.tensor(2.0, dtype=F64)},
    )
    base.update(changes)
    return tt.Problem(**base)


# ------------------------------------------------------------------------------------------- the probe
def test_the_probe_works_on_a_copy_and_names_an_in_place_write():
    x0 = torch.tensor([1.0, 0.5], dtype=F64)

    def in_place(x, u, p):
        x[0] = x[0] + 0.1 * x[1]
        return x

    with pytest.raises(ValueError, match=r"Problem.dynamics writes into its argument\(s\) x in place"):
        make(dynamics=in_place, x0=x0)
    assert x0.tolist() == [1.0, 0.5]  # the caller's tensor is untouched


@pytest.mark.parametrize("dynamics, advice", [
    (lambda x, u, p: torch.stack([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0].item()]), r"\.item\(\)"),
    (lambda x, u, p: torch.tensor([x[0] + 0.1 * x[1], x[1] + 0.1 * u[0]]), r"torch\.tensor\(\[\.\.\.\]\)"),
    (lambda x, u, p: torch.as_tensor(np.array(x) + 0.1), "numpy"),
    (lambda x, u, p: x if x[0] > 0 else x + 0.1 * u[0], "torch.where"),
], ids=["item", "tensor-of-entries", "numpy", "python-if"])
def test_code_that_torch_func_refuses_is_named_with_what_to_change(dynamics, advice):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # numpy's own warning about __array__
        with pytest.raises(ValueError, match=f"Problem.dynamics fails under torch.func.*{advice}"):
            make(dynamics=dynamics)


def test_an_in_place_write_into_a_new_tensor_and_a_failing_cost_are_named():
    def filled(x, u, p):
        y = torch.zeros(2, dtype=x.dtype)
        y[0] = x[0] + 0.1 * x[1]
        y[1] = x[1] + 0.1 * u[0]
        return y

    with pytest.raises(ValueError, match="Problem.dynamics fails under torch.func.*writes in place"):
        make(dynamics=filled)
    with pytest.raises(ValueError, match=r"Problem.stage_cost fails under torch.func.*\.item\(\)"):
        make(stage_cost=lambda x, u, p: (x * x).sum() + float(u[0]) ** 2)


def test_a_float64_constant_in_a_float32_problem_is_named():
    with pytest.raises(ValueError, match="Problem.dynamics returns torch.float64 in a torch.float32 problem"):
        make(x0=torch.tensor([1.0, 0.5]), params={"k": torch.tensor(2.0)},
             dynamics=lambda x, u, p: x + torch.tensor([0.1, 0.0], dtype=F64) * u[0])


def test_a_cut_graph_is_warned_about():
    with pytest.warns(UserWarning, match=r"Problem.dynamics: its value changes with x and u but its Jacobian .* "
                                         r"identically zero"):
        make(dynamics=lambda x, u, p: (x + 0.1 * u[0] * torch.ones_like(x)).detach())
    with pytest.warns(UserWarning, match=r"Problem.terminal_cost: its value changes with x"):
        make(terminal_cost=lambda x, p: (x * x).sum().detach())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a function constant in an argument is no cut graph
        make(stage_cost=lambda x, u, p: 0.5 * (u * u).sum())


# ----------------------------------------------------------------------------------------------- bounds
def test_nan_and_impossible_bounds_are_rejected():
    with pytest.raises(ValueError, match=r"Problem.u_lower holds NaN at \[0\]"):
        make(u_lower=torch.tensor([float("nan")]))
    inf = torch.tensor([float("inf")])
    with pytest.raises(ValueError, match="Problem.u_lower is inf at .*infeasible"):
        make(u_lower=inf, u_upper=inf)
    with pytest.raises(ValueError, match="Problem.x_upper is -inf at .*infeasible"):
        make(x_upper=torch.tensor([0.0, -float("inf")]))
    with pytest.raises(ValueError, match="u_lower exceeds Problem.u_upper at"):
        make(u_lower=torch.ones(1), u_upper=-torch.ones(1))


# ------------------------------------------------------------------------------------ parameter batches
def test_a_batched_parameter_given_to_the_constructor_is_an_error_at_the_solve():
    goals = torch.linspace(-1, 1, 8, dtype=F64).reshape(8, 1) * torch.tensor([1.0, 0.0], dtype=F64)
    prob = make(params={"k": torch.tensor(2.0, dtype=F64), "goal": goals},
                terminal_cost=lambda x, p: 10.0 * ((x - p["goal"]) ** 2).sum())
    with pytest.raises(ValueError, match=r"parameter 'goal' was given to the Problem constructor with shape \(8, 2\)"
                                         r".*with_params\(goal=values\)"):
        tt.solve(prob, torch.zeros(8, 2, dtype=F64))
    # one instance's value at construction, the batch through with_params: each instance its own goal
    one = make(params={"k": torch.tensor(2.0, dtype=F64), "goal": goals[0]},
               terminal_cost=lambda x, p: 10.0 * ((x - p["goal"]) ** 2).sum())
    sol = tt.solve(one.with_params(goal=goals), torch.zeros(8, 2, dtype=F64), options=tt.ILQROptions(
        cost_tolerance=1e-10, gradient_tolerance=1e-8))
    assert bool(sol.converged.all())
    final = sol.X[:, -1, 0]
    assert bool((final[1:] > final[:-1]).all())  # the end states follow the goals, not their mean
    # an (8, 2) parameter that is one instance's value, declared so
    declared = prob.replace(param_shapes={"k": (), "goal": (8, 2)})
    assert tt.solve(declared, torch.zeros(8, 2, dtype=F64)).X.shape == (8, 11, 2)


# ------------------------------------------------------------------------- horizons, replace, batches
def test_integer_horizons_from_numpy_are_accepted_and_bools_refused():
    prob = make(horizon=np.int64(12), nu=np.int32(1))
    assert type(prob.horizon) is int and prob.horizon == 12 and prob.u_init.shape == (12, 1)
    with pytest.raises(ValueError, match=r"Problem.horizon must be a positive int, got True \(a bool\)"):
        make(horizon=True)
    with pytest.raises(ValueError, match="Problem.horizon must be a positive int"):
        make(horizon=10.0)


def test_replace_with_a_new_horizon_resizes_the_guesses():
    prob = make(u_init=torch.tensor([0.3], dtype=F64))
    longer = prob.replace(horizon=20)
    assert longer.u_init.shape == (20, 1) and bool((longer.u_init == 0.3).all())
    varying = make(u_init=torch.arange(10, dtype=F64).reshape(10, 1),
                   X_init=torch.zeros(11, 2, dtype=F64)).replace(horizon=12)
    assert varying.u_init.reshape(-1).tolist() == list(range(10)) + [9.0, 9.0]
    assert varying.X_init.shape == (13, 2)
    assert make().replace(horizon=4).u_init.shape == (4, 1)


def test_an_empty_batch_is_named():
    with pytest.raises(ValueError, match=r"x0 holds an empty batch \(B = 0\)"):
        tt.solve(make(), torch.zeros(0, 2, dtype=F64))


# ---------------------------------------------------------------------------------------------- options
@pytest.mark.parametrize("method, options, message", [
    ("ilqr", tt.ILQROptions(iterations=0), r"ILQROptions.iterations must be an integer >= 1, got 0"),
    ("ilqr", tt.ILQROptions(cost_tolerance=-1e-6), r"ILQROptions.cost_tolerance must be >= 0"),
    ("ilqr", tt.ILQROptions(line_search_decrease=1.5), r"ILQROptions.line_search_decrease must be in \(0, 1\)"),
    ("ipm", tt.IPOptions(barrier_initial=-0.1), r"IPOptions.barrier_initial must be > 0"),
    ("ipm", tt.IPOptions(tolerance=-1e-8), r"IPOptions.tolerance must be >= 0"),
    ("altro", tt.ALTROOptions(penalty_initial=0.0), r"ALTROOptions.penalty_initial must be > 0"),
    ("altro", tt.ALTROOptions(iterations_outer=-2), r"ALTROOptions.iterations_outer must be an integer >= 1"),
    ("altro", tt.ALTROOptions(ilqr=tt.ILQROptions(iterations=0)), r"ALTROOptions.ilqr.iterations must be"),
    ("hm-ilqr", tt.HMILQROptions(cost_tolerance=float("nan")), r"HMILQROptions.cost_tolerance is NaN"),
])
def test_bad_option_values_name_the_field(method, options, message):
    with pytest.raises(ValueError, match=message):
        tt.solve(make(), method=method, options=options)


def test_bad_option_types_name_the_field():
    with pytest.raises(TypeError, match="ALTROOptions.ilqr must be an instance of ILQROptions, got ALTROOptions"):
        tt.solve(make(), method="altro", options=tt.ALTROOptions(ilqr=tt.ALTROOptions()))
    with pytest.raises(TypeError, match="ILQROptions.iterations must be an int"):
        tt.solve(make(), options=tt.ILQROptions(iterations=2.5))
    with pytest.raises(TypeError, match="ILQROptions.verbose must be True or False"):
        tt.solve(make(), options=tt.ILQROptions(verbose="yes"))
    with pytest.raises(TypeError, match=r"unknown field\(s\) \['iteration'\]"):
        tt.solve(make(), method="ilqr", options={"iteration": 3})


# ------------------------------------------------------------------------------------------------ duals
def test_warm_started_duals_are_checked_by_name_and_shape():
    prob = make(u_lower=-torch.ones(1, dtype=F64), u_upper=torch.ones(1, dtype=F64))
    with pytest.raises(ValueError, match=r"unknown constraint block\(s\) \['u_uper'\].*\['u_lower', 'u_upper'\]"):
        tt.solve(prob, method="altro", duals={"multipliers": {"u_uper": torch.zeros(10, 1)}})
    with pytest.raises(ValueError, match=r"duals\['multipliers'\]\['u_upper'\] has shape \(7, 1\)"):
        tt.solve(prob, method="altro", duals={"multipliers": {"u_upper": torch.zeros(7, 1)}})
    with pytest.raises(ValueError, match=r"duals has unknown entries \['multiplier'\]"):
        tt.solve(prob, method="altro", duals={"multiplier": {}})


# ---------------------------------------------------------------------------------------- default method
def test_the_default_method_respects_the_constraints():
    prob = make(u_lower=-0.5 * torch.ones(1, dtype=F64), u_upper=0.5 * torch.ones(1, dtype=F64))
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # no "ignores the constraints" (and not torch's deprecation
        # warning that forward AD's first use in a process raises)
        sol = tt.solve(prob)
    assert sol.method == "ipm" and bool(sol.converged.all()) and float(sol.max_violation.max()) < 1e-6
    with pytest.warns(UserWarning, match="ignores the constraints"):
        unconstrained = tt.solve(prob, method="ilqr")
    assert float(sol.U.abs().max()) <= 0.5 + 1e-6 and float(unconstrained.U.abs().max()) > 0.5
    assert tt.solve(make()).method == "ilqr"
    with pytest.warns(UserWarning, match="ignores the constraints"):
        assert tt.solve(prob, options=tt.ILQROptions(iterations=2)).method == "ilqr"  # the options say which


# ------------------------------------------------------------------------------------- MPC, logging, envs
def test_mpc_checks_its_method_at_construction():
    prob = make(u_lower=-torch.ones(1, dtype=F64), u_upper=torch.ones(1, dtype=F64))
    with pytest.raises(ValueError, match="unknown method 'newton'"):
        tt.MPC(prob, "newton")
    with pytest.warns(UserWarning, match="MPC: method 'ilqr' ignores the constraints"):
        mpc = tt.MPC(prob, "ilqr", 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # said once, at construction
        mpc(prob.x0)


def test_compile_on_a_method_without_compiled_kernels_warns_and_runs_eager(monkeypatch):
    # every shipped method has compiled kernels: HM-iLQR stands for a registered method without them, which must
    # then get options that ask for none (no kernel is compiled)
    from torchtraj.core import compiled as kernels

    monkeypatch.setattr(type(solvers.get("hm-ilqr")), "compiles", False)
    monkeypatch.setattr(kernels, "_KERNELS", {})
    prob = make(u_lower=-torch.ones(1, dtype=F64), u_upper=torch.ones(1, dtype=F64))
    with pytest.warns(UserWarning, match="method 'hm-ilqr' has no compiled kernels: compile=True runs it eager"):
        compiled = tt.solve(prob, method="hm-ilqr", options=tt.HMILQROptions(compile=True, iterations=3))
    eager = tt.solve(prob, method="hm-ilqr", options=tt.HMILQROptions(iterations=3))
    assert torch.equal(compiled.U, eager.U) and torch.equal(compiled.status, eager.status)
    with pytest.warns(UserWarning, match="MPC: method 'hm-ilqr' has no compiled kernels"):
        mpc = tt.MPC(prob, "hm-ilqr", 2, compile=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # said once, at construction
        mpc(prob.x0)
        tt.solve(prob, method="ipm", options=tt.IPOptions(iterations=2))  # compile off: nothing to say
    assert mpc.options.compile is False and not kernels._KERNELS


def test_verbose_leaves_the_logger_as_it_found_it():
    logger = logging.getLogger("torchtraj")
    level, handlers = logger.level, list(logger.handlers)
    tt.solve(make(), options=tt.ILQROptions(verbose=True, iterations=2))
    assert logger.level == level and logger.handlers == handlers


def test_environments_refuse_a_non_finite_start_state():
    envs = pytest.importorskip("envs")
    env = envs.PendulumEnv()
    with pytest.raises(ValueError, match="options\\['state'\\] must be finite"):
        env.reset(options={"state": np.array([np.nan, 0.0])})


def test_max_iterations_says_which_limit_was_hit():
    prob = make(u_lower=-0.2 * torch.ones(1, dtype=F64), u_upper=0.2 * torch.ones(1, dtype=F64))
    sol = tt.solve(prob, method="al-ilqr", options=tt.ALTROOptions(iterations_outer=1, projection=False))
    assert sol.status[0] == tt.Status.MAX_ITERATIONS
    assert "max_iterations: 1 after the outer loop's limit (iterations_outer" in sol.summary()
