"""Solves inside a caller's ``torch.inference_mode``.

Every method solves there (the KKT certificate took its gradient by autograd, which records nothing in inference mode,
and raised) and gets the same solution, bit for bit, as outside it; ``tt.MPC`` acts the same inside it.
"""

import dataclasses
import warnings

import gymnasium as gym
import pytest
import torch

import torchtraj as tt
from torchtraj import problems, solvers

F64 = torch.float64


def pendulum(method: str) -> tt.Problem:
    """The pendulum over N = 10 without its terminal goal (torque bound active at the start); unconstrained for a
    method that ignores constraints."""
    name = "pendulum" if solvers.get(method).handles_constraints else "pendulum_unconstrained"
    return problems.get(name).replace(horizon=10, u_init=torch.zeros(1, dtype=F64), terminal_eq=None)


def tensors(value, path="solution"):
    """``(path, tensor)`` of every tensor in a solution, its history, dicts and lists."""
    if isinstance(value, torch.Tensor):
        yield path, value
    elif isinstance(value, dict):
        for k, v in value.items():
            yield from tensors(v, f"{path}[{k!r}]")
    elif isinstance(value, (list, tuple)):
        for i, v in enumerate(value):
            yield from tensors(v, f"{path}[{i}]")
    elif dataclasses.is_dataclass(value):
        for f in dataclasses.fields(value):
            yield from tensors(getattr(value, f.name), f"{path}.{f.name}")


def solved(method, problem, x0, **kwargs):
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*ignores the constraints")
        return tt.solve(problem, x0, method, **kwargs)


@pytest.mark.parametrize("method", solvers.names())
def test_a_solve_inside_inference_mode_is_the_solve_outside_it(method):
    x0 = problems.sample_x0("pendulum", 3, seed=0)
    outside = solved(method, pendulum(method), x0)
    with torch.inference_mode():
        inside = solved(method, pendulum(method), x0)
    assert inside.status.tolist() == outside.status.tolist() and bool(outside.converged.all()), outside.status
    pairs = dict(tensors(outside))
    found = dict(tensors(inside))
    assert found.keys() == pairs.keys()
    for path, t in found.items():
        assert t.is_inference(), path  # made in the caller's inference mode, as everything there
        assert torch.equal(t, pairs[path]), path


def test_mpc_acts_the_same_inside_inference_mode():
    def actions(inside: bool):
        env = gym.make("torchtraj/Pendulum-v0").unwrapped
        policy = tt.MPC(env.problem(horizon=20), "ipm", 2)
        obs, _ = env.reset(seed=0)
        out = []
        for _ in range(4):
            if inside:
                with torch.inference_mode():
                    action = policy(obs)
            else:
                action = policy(obs)
            out.append(action)
            obs, *_ = env.step(action)
        return out

    for a, b in zip(actions(True), actions(False)):
        assert (a == b).all()
