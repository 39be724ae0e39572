"""Planners on rollouts that diverge: the plan stays finite."""
import pytest
import torch

from gnwarp.control.sampling import SamplingConfig, SamplingPlanner


class Diverged:
    """Rollout dynamics whose rollouts are all NaN (a learned model gone unstable), but for
    ``finite`` rows (a reward of 1 a step there)."""
    device = torch.device("cpu")

    def __init__(self, finite=()):
        self.finite = list(finite)

    def rollout(self, obs, actions, samples):
        s = torch.full((actions.shape[0], actions.shape[1] + 1, 2, 13), float("nan"))
        s[self.finite] = 1.0
        return s


def _rest(n, bodies):
    """Body states at rest: zeros but the unit quaternions (a planner refuses ~zero ones)."""
    x = torch.zeros(n, bodies, 13)
    x[..., 3] = 1.0
    return x


def _planner(dynamics, method):
    return SamplingPlanner(dynamics, lambda s, a: s[:, 1:, 1, 0].sum(1), [[-1.0, 1.0]], 2,
                           SamplingConfig(horizon=4, samples=8, knots=2, method=method, noise=0.5))


@pytest.mark.parametrize("method", ["best", "mppi"])
def test_every_rollout_diverged_keeps_the_nominal(method):
    p = _planner(Diverged(), method)
    nominal = p.nominal().clone()
    a = p.step(_rest(2, 2))
    assert torch.isfinite(a).all()
    torch.testing.assert_close(p.plan, nominal)


def test_mppi_weights_only_finite_rollouts():
    # episode 0's candidate 3 is the one finite rollout: MPPI picks it alone; episode 1 keeps its nominal
    p = _planner(Diverged(finite=[3]), "mppi")
    cand = None
    orig = p.candidates

    def spy():
        nonlocal cand
        cand = orig()
        return cand
    p.candidates = spy
    p.step(_rest(2, 2))
    torch.testing.assert_close(p.plan[0], p.actions(cand[0, 3]))
    torch.testing.assert_close(p.plan[1], p.actions(cand[1, 0]))
