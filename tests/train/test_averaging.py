"""The running average of the parameters (`recon.train.averaging`): its weights (a worked
example), the average against its closed form (a brute-force twin) and its limiting cases."""

import pytest
import torch

from recon.train.averaging import ParameterAverage, average_weight


def test_the_weights_are_a_mean_until_the_window_is_full_then_exponential():
    assert [average_weight(n, 3) for n in (1, 2, 3, 4, 10)] == pytest.approx(
        [1.0, 1 / 2, 1 / 3, 1 / 3, 1 / 3]
    )
    assert average_weight(5, 2.5) == pytest.approx(0.4)  # a fractional window
    for count, window in ((0, 3), (1, 0.5)):
        with pytest.raises(ValueError):
            average_weight(count, window)


def _closed_form(xs: list[torch.Tensor], window: int) -> torch.Tensor:
    """The mean of the first `window` values, decayed by (1 - 1/window) a value since, plus
    each later value's share 1/window (1 - 1/window)^(age)."""
    n, w = len(xs), min(len(xs), window)
    mean = torch.stack(xs[:w]).mean(0)
    keep = 1.0 - 1.0 / window
    out = mean * keep ** (n - w)
    for k in range(w, n):
        out = out + xs[k] * (1.0 / window) * keep ** (n - 1 - k)
    return out


@pytest.mark.parametrize("window", [1, 3, 7])
def test_the_running_average_is_its_closed_form(window):
    g = torch.Generator().manual_seed(window)
    xs = [torch.randn(5, 2, generator=g, dtype=torch.float64) for _ in range(12)]
    average = ParameterAverage([xs[0]])
    for x in xs[1:]:
        average.update([x], window)
    assert average.count == 12
    torch.testing.assert_close(average.values[0], _closed_form(xs, window))
    if window == 1:  # a window of one step: the last value
        torch.testing.assert_close(average.values[0], xs[-1])


def test_a_constant_stays_itself_and_the_average_does_not_alias_its_inputs():
    x = torch.full((4,), 0.25)
    average = ParameterAverage([x])
    for _ in range(5):
        average.update([x], 2)
    torch.testing.assert_close(average.values[0], x)
    x.add_(1.0)  # the parameter moves on; the average keeps its own copy
    assert float(average.values[0][0]) == 0.25


def test_it_copies_into_matching_tensors_and_round_trips_its_state():
    a, b = torch.zeros(3), torch.ones(2, 2)
    average = ParameterAverage([a, b])
    average.update([a + 2, b + 2], 4)  # mean of two: +1
    assert average.matches([a, b]) and not average.matches([a]) and not average.matches([a, a])
    restored = ParameterAverage.from_state_dict(average.state_dict())
    assert restored.count == 2
    restored.copy_to([a, b])
    torch.testing.assert_close(a, torch.ones(3))
    torch.testing.assert_close(b, torch.full((2, 2), 2.0))
    with pytest.raises(ValueError):
        restored.copy_to([torch.zeros(4), b])
