"""The split of the parameters into shared and batched ones, kept between calls (``core.batching._split_params``)."""

import torch

from torchtraj.bench.ops import OperatorCounter
from torchtraj.core import batching
from torchtraj.core.batching import map_stage


def _dynamics(x, u, p):
    return p["a"] * x + p["b"] * u


def _params(B: int) -> dict:
    shared = torch.tensor([2.0, 3.0], dtype=torch.float64).expand(B, 2)  # one instance's value for all
    batched = torch.arange(B, dtype=torch.float64).unsqueeze(-1).expand(B, 2).contiguous()
    return {"a": shared, "b": batched}


def test_the_split_of_the_same_parameters_is_made_once():
    params = _params(3)
    X, U = torch.ones(3, 4, 2, dtype=torch.float64), torch.ones(3, 4, 2, dtype=torch.float64)
    first = map_stage(_dynamics, X, U, params)
    with OperatorCounter() as again:
        batching._split_params(params)
    other = dict(params, a=torch.tensor([2.0, 3.0], dtype=torch.float64).expand(3, 2))
    with OperatorCounter() as fresh:
        batching._split_params(other)
    assert again.total == 0  # kept: no view of the shared value made again
    assert fresh.total == 1  # another tensor: split afresh, one view of its shared value
    assert torch.equal(map_stage(_dynamics, X, U, params), first)


def test_a_kept_split_sees_changes_in_place_and_not_replaced_tensors():
    base = torch.tensor([2.0, 3.0], dtype=torch.float64)
    params = dict(_params(2), a=base.expand(2, 2))
    X, U = torch.ones(2, 3, 2, dtype=torch.float64), torch.zeros(2, 3, 2, dtype=torch.float64)
    assert torch.equal(map_stage(_dynamics, X, U, params), torch.tensor([2.0, 3.0]).double().expand(2, 3, 2))
    base.add_(1.0)  # in place: the kept view sees it
    assert torch.equal(map_stage(_dynamics, X, U, params), torch.tensor([3.0, 4.0]).double().expand(2, 3, 2))
    params["a"] = torch.tensor([5.0, 6.0], dtype=torch.float64).expand(2, 2)  # replaced: another key
    assert torch.equal(map_stage(_dynamics, X, U, params), torch.tensor([5.0, 6.0]).double().expand(2, 3, 2))


def test_parameters_that_require_grad_or_are_transformed_are_split_afresh():
    params = _params(2)
    a = params["a"].detach().clone().requires_grad_(True)
    X, U = torch.ones(2, 3, 2, dtype=torch.float64), torch.ones(2, 3, 2, dtype=torch.float64)
    (grad,) = torch.autograd.grad(map_stage(_dynamics, X, U, dict(params, a=a)).sum(), a)
    assert torch.equal(grad, torch.full((2, 2), 3.0, dtype=torch.float64))
    assert batching._split_key(dict(params, a=a)) is None

    def mapped(b):  # the parameters batched by an outer vmap: wrapped tensors, never kept
        assert batching._split_key(dict(params, b=b)) is None
        return map_stage(_dynamics, X, U, dict(params, b=b))

    outer = torch.stack([params["b"], params["b"] + 1.0])
    out = torch.func.vmap(mapped)(outer)
    for i in range(2):
        assert torch.equal(out[i], map_stage(_dynamics, X, U, dict(params, b=outer[i])))


def test_no_batch_sized_parameter_outlives_its_maps():
    import gc
    import weakref

    params = _params(4)
    batched = weakref.ref(params["b"])
    map_stage(_dynamics, torch.ones(4, 3, 2, dtype=torch.float64), torch.ones(4, 3, 2, dtype=torch.float64), params)
    assert batching._split_key(params) in batching._SPLITS  # kept
    del params
    gc.collect()
    assert batched() is None  # the split keeps the shared values' views, not the batched tensors
