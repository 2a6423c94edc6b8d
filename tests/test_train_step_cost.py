"""The train-step cost benchmark (`python -m benchmarks.train_step_cost`) times the losses it names."""

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cost(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))          # `benchmarks` lives at the repository root
    sys.modules.pop("benchmarks", None)
    import benchmarks.train_step_cost as cost
    return cost


def test_its_own_variants_compute_the_library_loss(cost):
    """Same weights and noise: the one-call central difference gives the library's
    finite-difference loss, the forward difference the JVP loss to its 1e-5 step's error."""
    size = (32, 1, 2, 1)
    g = torch.Generator().manual_seed(0)
    batch = {"state": torch.randn(16, 39, generator=g), "actions": torch.randn(16, 16, 4, generator=g)}
    losses = {}
    for name, dudt, how in [("fd", "finite_difference", None), ("jvp", "jvp", None),
                            ("one_call", None, "one_call"), ("forward", None, "forward")]:
        policy = cost._policy("mean_flow", size, **({"meanflow_dudt": dudt} if dudt else {}))
        torch.manual_seed(5)
        losses[name] = (policy.compute_loss(batch).loss if how is None else cost._local_loss(policy, batch, how)).item()
    assert losses["one_call"] == pytest.approx(losses["fd"], rel=1e-5)
    assert losses["forward"] == pytest.approx(losses["jvp"], rel=1e-3)
    assert losses["fd"] == pytest.approx(losses["jvp"], rel=1e-4)


def test_timing_rows_are_finite_ratios_to_flow_matching(cost, monkeypatch):
    monkeypatch.setattr(cost, "BATCH", 8)
    res = cost.time_size("tiny", (32, 1, 2, 1), reps=1, warmup=0)
    names = [row["variant"] for row in res["rows"]]
    assert names == ["FM", "jvp", "finite_difference", "fd, one call (B + 2n rows)", "forward difference (n rows)"]
    assert all(row["step_ms"] > 0 and 0 < row["vs_fm"] < float("inf") for row in res["rows"])
    assert "| tiny | finite_difference |" in cost.table([res])
