"""The barrier continuation's step to the next weight, per instance
(:func:`torchtraj.solvers.eilqr.verdicts.reweighted`): compiled solves make it inside the kernel of the move, for
every instance by masks, where an eager solve makes it only where some stage ended."""

import dataclasses

import torch

import torchtraj as tt
from torchtraj.core.constraints import Constraints
from torchtraj.solvers.eilqr.continuation import barrier_multipliers, rows_at, weights_for
from torchtraj.solvers.eilqr.merit import MeritMemory
from torchtraj.solvers.eilqr.model import Iterate, expand, with_weight
from torchtraj.solvers.eilqr.newton import empty_multipliers
from torchtraj.solvers.eilqr.verdicts import _WEIGHED, reweighted

F64 = torch.float64


def model_of_two_instances():
    """The pendulum's expansion (its control bounds are the barrier's rows) at two perturbed guesses."""
    torch.manual_seed(3)
    problem = tt.problems.get("pendulum").replace(horizon=8)
    cons, params, opts = Constraints.of(problem), problem.batched_params(2), tt.EILQROptions()
    x0 = problem.x0.expand(2, -1).clone()
    X = x0.unsqueeze(1) + 0.1 * torch.randn(2, problem.N + 1, problem.nx, dtype=F64)
    U = 3.0 * torch.randn(2, problem.N, problem.nu, dtype=F64)  # some beyond the bounds: the relaxed barrier
    weights = weights_for(torch.tensor([1e-2, 1e-2], dtype=F64), opts)
    z, zN = barrier_multipliers(rows_at(cons, X, U, params), weights)
    it = Iterate(X, U, *empty_multipliers(X, cons.me, cons.meN, 0), z=z, zN=zN)
    return problem, cons, params, opts, it, weights, expand(problem, cons, params, it, x0, None, weights)


def test_a_new_weight_moves_the_instances_whose_stage_ended_alone():
    problem, cons, params, opts, it, weights, model = model_of_two_instances()
    memory = MeritMemory(torch.randn(2, 3, dtype=F64), torch.rand(2, 3, dtype=F64))
    advance = torch.tensor([True, False])
    moved, new_weights, new_model, new_memory = reweighted(model, it, weights, memory, advance, 1e-8, opts)
    assert new_weights.weight[0] < weights.weight[0] and new_weights.weight[1] == weights.weight[1]
    expected = with_weight(model, new_weights)
    for field in dataclasses.fields(model):
        value, before, after = getattr(new_model, field.name), getattr(model, field.name), getattr(expected, field.name)
        if not isinstance(value, torch.Tensor):
            continue
        assert torch.equal(value[1], before[1]), field.name  # the other instance's model, to the bit
        assert torch.equal(value[0], after[0]), field.name  # the new weight's model
    assert torch.isinf(new_memory.J[0]).all() and torch.equal(new_memory.J[1], memory.J[1])
    assert torch.equal(moved.z, model.z) and torch.equal(moved.X, it.X)


def test_the_fields_a_weight_sets_are_those_reweighted_takes():
    """Every field of the model that :func:`with_weight` changes is one of ``_WEIGHED`` (a field missed there would
    keep the old weight's value where a stage ended)."""
    problem, cons, params, opts, it, weights, model = model_of_two_instances()
    other = with_weight(model, weights_for(weights.weight / 10, opts))
    changed = {field.name for field in dataclasses.fields(model)
               if isinstance(getattr(model, field.name), torch.Tensor)
               and not torch.equal(getattr(model, field.name), getattr(other, field.name))}
    assert changed and changed <= set(_WEIGHED), changed - set(_WEIGHED)
