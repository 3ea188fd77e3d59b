"""The rounds of a backtracking line search (``globalization.line_search.backtrack``) and the interior point's first
round of the full step alone (``IPOptions.line_search_first``).

The rounds decide which candidates are evaluated together, never which one is taken: each instance takes its first
accepted step size in the order ``α_0 > α_1 > …``. So a solve whose first round evaluates the full step alone takes
the same steps, to the bit, as one whose first round evaluates four.
"""

import pytest
import torch

import torchtraj as tt
from torchtraj.globalization.line_search import Accepted, backtrack
from torchtraj.solvers.ipm.line_search import FULL_STEP_ALONE_FROM, batch_first_round, first_round


def _accept_from(first_accepted: torch.Tensor):
    """An acceptance test that accepts candidate ``j`` of instance ``b`` from ``first_accepted[b]`` on, and records
    the step sizes of each round."""
    rounds = []

    def evaluate(alphas, rows=None):
        rounds.append(alphas.clone())
        start = first_accepted if rows is None else first_accepted[rows]
        index = torch.log2(1 / alphas).round().long().expand(start.shape[0], -1)  # α_j = 2^-j
        accept = index >= start.unsqueeze(1)
        return accept, (index,)

    return evaluate, rounds


@pytest.mark.parametrize("first_round, sizes", [(None, [3, 3, 2]), (1, [1, 3, 3]), (2, [2, 3, 3]), (5, [5, 3])])
def test_rounds_of_any_size_take_each_instances_first_accepted_step(first_round, sizes):
    steps = 0.5 ** torch.arange(8, dtype=torch.float64)
    first_accepted = torch.tensor([0, 6, 2, 4])  # the index of each instance's first acceptable candidate
    evaluate, rounds = _accept_from(first_accepted)
    start = Accepted(torch.zeros(4, dtype=torch.bool), torch.zeros(4, dtype=torch.float64), (torch.zeros(4).long(),))
    out = backtrack(steps, 3, evaluate, torch.ones(4, dtype=torch.bool), start, first_round=first_round)
    assert out.found.all()
    torch.testing.assert_close(out.alpha, steps[first_accepted], rtol=0, atol=0)
    assert out.values[0].tolist() == first_accepted.tolist()
    assert [r.shape[-1] for r in rounds] == sizes  # until instance 1 found its step (candidate 6)
    assert torch.cat(rounds).tolist() == steps[:sum(sizes)].tolist()  # every candidate once, in order


def test_a_first_round_of_the_full_step_alone_takes_the_same_steps(monkeypatch):
    """Eager solves of a batch, the first round's candidates four (the default there) or one: the same solution to
    the bit, and the full step alone in a round of its own (its later rounds evaluate four)."""
    from torchtraj.solvers.ipm import line_search

    sizes = []
    trial = line_search.trial
    monkeypatch.setattr(line_search, "trial", lambda *args: sizes.append(args[12].shape[1]) or trial(*args))
    for name in ("pendulum", "cartpole"):
        problem = tt.problems.get(name).replace(horizon=30)
        x0 = tt.problems.sample_x0(name, 4, seed=0)
        sizes.clear()
        four = tt.solve(problem, x0, "ipm")
        assert set(sizes) == {4}
        sizes.clear()
        one = tt.solve(problem, x0, "ipm", options=tt.IPOptions(line_search_first=1))
        assert sizes.count(1) > sizes.count(4) > 0, "the full step alone, and some later rounds of four"
        assert torch.equal(four.iterations, one.iterations) and torch.equal(four.status, one.status)
        for field in ("X", "U", "cost", "costate"):
            assert torch.equal(getattr(four, field), getattr(one, field)), (name, field)


def test_the_full_step_alone_is_the_first_round_of_large_compiled_batches_on_a_cpu():
    cpu = torch.device("cpu")
    decided = lambda B, **options: first_round(batch_first_round(tt.IPOptions(**options), B, cpu))  # noqa: E731
    assert decided(FULL_STEP_ALONE_FROM, compile=True) == 1
    assert decided(FULL_STEP_ALONE_FROM - 1, compile=True) == 4
    assert decided(4096) == 4  # eager: a round's cost is its calls, whatever its candidates
    assert decided(4096, compile=True, line_search_parallel=2) == 1
    assert decided(4096, compile=True, line_search_first=3) == 3  # given: kept
    assert decided(1, line_search_parallel=6) == 6


def test_a_first_round_of_no_candidate_is_refused():
    with pytest.raises(ValueError, match="line_search_first must be None or >= 1, got 0"):
        tt.IPOptions(line_search_first=0)
