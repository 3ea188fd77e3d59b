"""tt.MPC: what one control step applies, the warm start and its reset, batching, and closed-loop episodes.

Default run: the policy's contract (first control of tt.solve from the shifted warm start, clamped), per-instance
resets under a vector environment's autoreset, failure isolation, seeded determinism, vector-versus-single
equivalence, and short episodes on a few seeds that must succeed. ``-m slow``: the acceptance runs (100 seeded
episodes per task, a 64-environment vector run with autoresets, Pendulum-v1 over 20 seeds).
"""

import dataclasses
import importlib.util
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import envs
import torchtraj as tt
from torchtraj.bench import mpc as bench
from torchtraj.mpc import DEFAULT_ALTRO

ROOT = Path(__file__).resolve().parents[1]


def pendulum_mpc(iterations=2, **kwargs):
    env = envs.PendulumEnv()
    return tt.MPC(bench.pendulum_problem(env), "altro", iterations, **kwargs), env


def step_options(iterations):
    return dataclasses.replace(DEFAULT_ALTRO, iterations_inner=iterations, iterations_outer=1)


# a swing (bound active), one near upright (bound inactive), one hanging
STATES = torch.tensor([[0.3, 2.0], [3.0, 0.2], [0.05, 0.0]], dtype=torch.float64)


# ---------------------------------------------------------------------------------------------- one control step
def test_first_control_is_the_solvers_first_control_clamped_to_the_bounds():
    mpc, _ = pendulum_mpc()
    u = mpc(STATES)
    sol = tt.solve(mpc.problem, STATES, "altro", options=step_options(2))
    torch.testing.assert_close(u, sol.U[:, 0].clamp(-3.0, 3.0), rtol=0, atol=1e-12)
    assert sol.U[:, 0].abs().max() > 3.0  # the clamp is exercised: 2 iterations leave the bound slightly violated
    assert u.abs().max() <= 3.0
    torch.testing.assert_close(mpc.U, sol.U, rtol=0, atol=1e-12)
    assert mpc.X.shape == (3, 31, 2) and mpc.status.shape == (3,)
    assert (mpc.status == tt.Status.MAX_ITERATIONS).any()  # within budget, not converged: still applied


def test_warm_start_is_the_shifted_solution_and_the_next_step_solves_from_it():
    mpc, _ = pendulum_mpc()
    mpc(STATES)
    first = mpc.solution
    U0, duals = mpc.warm_start()
    torch.testing.assert_close(U0[:, :-1], first.U[:, 1:], rtol=0, atol=0)
    torch.testing.assert_close(U0[:, -1], first.U[:, -1], rtol=0, atol=0)
    for name, lam in first.multipliers.items():
        torch.testing.assert_close(duals["multipliers"][name][:, :-1], lam[:, 1:], rtol=0, atol=0)
    assert any(lam[:, 1:].abs().max() > 0 for lam in first.multipliers.values())  # multipliers really carried
    assert "penalties" not in duals  # penalties restart at penalty_initial (module docstring)
    x1 = first.X[:, 1]
    u = mpc(x1)
    sol = tt.solve(mpc.problem, x1, "altro", U0=U0, options=step_options(2), duals=duals)
    torch.testing.assert_close(u, sol.U[:, 0].clamp(-3.0, 3.0), rtol=0, atol=1e-12)
    cold = tt.solve(mpc.problem, x1, "altro", options=step_options(2))
    assert (sol.U - cold.U).abs().max() > 1e-3  # the warm start changes the answer


def test_reset_drops_the_warm_start_of_masked_instances_only():
    mpc, _ = pendulum_mpc()
    mpc(STATES)
    shifted, duals = mpc.warm_start()
    mpc.reset(np.array([False, True, False]))
    U0, after = mpc.warm_start()
    torch.testing.assert_close(U0[1], mpc.problem.u_init, rtol=0, atol=0)
    torch.testing.assert_close(U0[[0, 2]], shifted[[0, 2]], rtol=0, atol=0)
    for name, lam in after["multipliers"].items():
        assert lam[1].abs().max() == 0
        torch.testing.assert_close(lam[[0, 2]], duals["multipliers"][name][[0, 2]], rtol=0, atol=0)
    mpc.reset()
    assert torch.equal(mpc.warm_start()[0], mpc.problem.u_init.expand(3, -1, -1))
    with pytest.raises(ValueError, match="mask"):
        mpc.reset(np.array([True, False]))


def test_observation_kinds_and_unbatched_calls():
    mpc, _ = pendulum_mpc()
    out = mpc(STATES.numpy())
    assert isinstance(out, np.ndarray) and out.shape == (3, 1) and out.dtype == np.float64
    mpc.reset()
    single = mpc(STATES[0].to(torch.float32))
    assert isinstance(single, torch.Tensor) and single.shape == (1,) and single.dtype == torch.float32
    np.testing.assert_allclose(single.numpy(), out[0], rtol=1e-6, atol=1e-6)  # float32 rounding of the state


def test_a_failing_instance_changes_no_other_and_applies_its_warm_start():
    mpc, _ = pendulum_mpc()
    bad = STATES.clone()
    bad[1] = float("nan")
    u = mpc(bad)
    assert mpc.status[1] == tt.Status.NON_FINITE
    assert torch.equal(u[1], mpc.problem.u_init[0])  # cold start control, as there was no warm start
    assert not mpc._warm[1] and mpc._warm[[0, 2]].all()
    alone, _ = pendulum_mpc()
    torch.testing.assert_close(u[[0, 2]], alone(STATES[[0, 2]]), rtol=0, atol=1e-10)


def test_per_call_parameters_rebuild_the_problem_only_when_they_change():
    env = envs.CarEnv()
    mpc = bench.controller("car", env)
    obs = np.stack([env.reset(seed=s)[0] for s in (0, 1)])
    mpc(obs)
    problem = mpc.problem
    assert torch.equal(problem.params["obstacles"], torch.as_tensor(obs[:, 3:]).reshape(2, -1, 3))
    mpc(obs)
    assert mpc.problem is problem
    obs[1, 3] += 0.1
    mpc(obs)
    assert mpc.problem is not problem and mpc.problem.params["obstacles"][1, 0, 0] == obs[1, 3]


def test_construction_errors_name_the_argument():
    problem = bench.pendulum_problem(envs.PendulumEnv())
    with pytest.raises(ValueError, match="method"):
        tt.MPC(problem, "newton")
    with pytest.raises(ValueError, match="iterations"):
        tt.MPC(problem, iterations=0)
    with pytest.raises(TypeError, match="ALTROOptions"):
        tt.MPC(problem, options=tt.ILQROptions())
    with pytest.raises(TypeError, match="Problem"):
        tt.MPC("pendulum")
    with pytest.raises(ValueError, match="observation_to_state"):
        tt.MPC(problem)(np.zeros((2, 3)))
