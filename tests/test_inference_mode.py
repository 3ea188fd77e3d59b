"""Solves without gradients run under ``torch.inference_mode`` (``torchtraj/solve.py``, ``_without_autograd``).

A solve that nothing differentiates runs every operator without autograd's bookkeeping, and returns its solution as
normal tensors. Checked here: every method solves inside a caller's ``torch.inference_mode`` (the KKT certificate took
its gradient by autograd, which records nothing there, and raised) and gets the same solution, bit for bit, as
outside it; a returned solution's tensors can be changed in place and saved for backward, which inference tensors
cannot; what a solve keeps on its problem (the constraints' layout, the IPM's scaled and restoration problems,
eILQR's barrier problems) is made outside inference mode, so that a later differentiable solve of the same problem
object gets the gradient a fresh one gets; and ``tt.MPC`` acts the same inside inference mode.
"""

import dataclasses
import importlib
import warnings

import gymnasium as gym
import pytest
import torch

import torchtraj as tt
from torchtraj import problems, solvers
from torchtraj.core.derivatives import differentiates_in_inference_mode

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
    # made in the caller's inference mode, as everything there; outside it where this PyTorch's torch.func returns
    # zeros in inference mode (then it matters that the solve is the same)
    made_inside = differentiates_in_inference_mode()
    for path, t in found.items():
        assert t.is_inference() == made_inside, path
        assert torch.equal(t, pairs[path]), path


def test_a_solution_is_made_of_normal_tensors():
    x0 = problems.sample_x0("pendulum", 2, seed=0)
    sol = tt.solve(pendulum("ipm"), x0, "ipm")
    inference = [path for path, t in tensors(sol) if t.is_inference()]
    assert not inference
    weights = torch.ones(2, dtype=F64, requires_grad=True)
    (sol.cost * weights).sum().backward()  # the product saves sol.cost for backward
    assert torch.equal(weights.grad, sol.cost)
    before = sol.U.clone()
    sol.U.mul_(2.0)  # changed in place outside inference mode
    assert torch.equal(sol.U, 2.0 * before)


def kept(value, depth=0):
    """The tensors a solve keeps on a problem: in its private attributes (the constraints' layout, the IPM's scaled
    and restoration problems, eILQR's barrier problems), the objects, problems, dicts and tuples they hold."""
    if isinstance(value, torch.Tensor):
        yield value
    elif depth < 4 and isinstance(value, (dict, list, tuple)):
        for v in (value.values() if isinstance(value, dict) else value):
            yield from kept(v, depth + 1)
    elif depth < 4 and hasattr(value, "__dict__") and not callable(value):
        items = vars(value).items()
        for k, v in items:
            if depth > 0 or k.startswith("_"):
                yield from kept(v, depth + 1)


@pytest.mark.parametrize("method, name", [(m, "car_3obs") for m in solvers.names()] + [("ipm", "cartpole")])
def test_what_a_solve_keeps_on_its_problem_is_not_made_in_inference_mode(method, name):
    problem = problems.get(name).replace(horizon=12)
    solved(method, problem, problems.sample_x0(name, 2, seed=0), options=solvers.get(method).step_options(None, 3))
    if name == "cartpole":  # its cost gradient at the guess is large: the IPM keeps the scaled problem
        assert "_objective_scaled" in vars(problem)
    found = list(kept(problem))
    assert found  # the constraints' layout at least
    assert not any(t.is_inference() for t in found)  # a later differentiable solve's autograd may save them


@pytest.mark.parametrize("method", ["ipm", "eilqr", "altro"])
def test_a_differentiable_solve_after_one_without_gradients(method):
    """The same problem object solved without gradients, then differentiated with respect to ``x0``: the second
    solve uses what the first kept on the problem, and its gradient is a fresh problem's."""
    x0 = problems.sample_x0("pendulum", 2, seed=0)

    def gradient(problem):
        start = x0.clone().requires_grad_(True)
        sol = tt.solve(problem, start, method)
        assert bool(sol.converged.all()), sol.status
        sol.cost.sum().backward()
        return start.grad

    reused = pendulum(method)
    tt.solve(reused, x0, method)
    assert torch.equal(gradient(reused), gradient(pendulum(method)))


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


def test_a_solve_under_a_dispatch_mode_runs_outside_inference_mode():
    """A dispatch mode (the operator counter of ``torchtraj.bench.ops``, a trace) sees other calls in inference mode
    (composite operators whole): under one, a solve runs as it did before, so that counts stay comparable."""
    from torch.utils._python_dispatch import TorchDispatchMode

    class Modes(TorchDispatchMode):
        inference = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            Modes.inference += torch.is_inference_mode_enabled()
            return func(*args, **(kwargs or {}))

    with Modes():
        sol = tt.solve(pendulum("ipm"), problems.sample_x0("pendulum", 2, seed=0), "ipm")
    assert bool(sol.converged.all()) and Modes.inference == 0
    Modes.inference = 0
    with Modes(), torch.inference_mode():  # the caller's own inference mode is kept
        tt.solve(pendulum("ipm"), problems.sample_x0("pendulum", 2, seed=0), "ipm")
    assert Modes.inference > 0


def test_where_torch_func_returns_zeros_in_inference_mode_a_solve_runs_under_no_grad(monkeypatch):
    """PyTorch releases before the fix of pytorch/pytorch#177318 (2.11 among them) return zero derivatives from
    ``torch.func`` under inference mode, and every method would stall at its initial guess. Where the probe says so,
    a method's iterations run under ``torch.no_grad`` outside inference mode, the caller's included, and the solution
    is the same. (This PyTorch has the fix: the probe is faked here; the true probe is checked below.)"""
    solve_module = importlib.import_module("torchtraj.solve")  # the package's ``solve`` is the function
    seen = []
    original = solvers.get("ipm").solve

    def spy(self, *args, **kwargs):
        seen.append((torch.is_inference_mode_enabled(), torch.is_grad_enabled()))
        return original(*args, **kwargs)

    x0 = problems.sample_x0("pendulum", 3, seed=0)
    reference = solved("ipm", pendulum("ipm"), x0)
    monkeypatch.setattr(solve_module, "differentiates_in_inference_mode", lambda: False)
    monkeypatch.setattr(type(solvers.get("ipm")), "solve", spy)
    outside = solved("ipm", pendulum("ipm"), x0)
    with torch.inference_mode():
        inside = solved("ipm", pendulum("ipm"), x0)
    assert seen == [(False, False), (False, False)]
    for sol in (outside, inside):
        assert sol.status.tolist() == reference.status.tolist() and torch.equal(sol.X, reference.X)
        assert not sol.X.is_inference()


def test_the_probe_of_torch_func_in_inference_mode_answers_for_this_pytorch_unseen_by_dispatch_modes():
    """The probe's answer is what ``torch.func.grad`` does under inference mode in the installed PyTorch; made
    under a dispatch mode (the operator counter of ``torchtraj.bench.ops``), it adds no call to the count."""
    from torch.func import grad

    from torchtraj.bench.ops import OperatorCounter

    x = torch.tensor(3.0, dtype=F64)
    with torch.inference_mode():
        derivative = grad(lambda x: x ** 3)(x)
    differentiates_in_inference_mode.cache_clear()
    with OperatorCounter() as counter:
        answer = differentiates_in_inference_mode()
    assert answer == bool(derivative == 27.0)
    assert counter.total == 0
