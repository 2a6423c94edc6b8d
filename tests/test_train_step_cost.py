"""The train-step cost benchmark (`python -m benchmarks.train_step_cost`) times the losses it names."""

import functools
import json
import sys
from pathlib import Path

import pytest
import torch

from action_decoder import ActionDecoderPolicy, DecoderConfig

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cost(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))          # `benchmarks` lives at the repository root
    sys.modules.pop("benchmarks", None)
    import benchmarks.train_step_cost as cost
    return cost


def test_its_own_variants_compute_the_library_loss(cost):
    """Same weights and noise: both batchings of the central difference give the library's
    finite-difference loss, the forward difference the JVP loss to its 1e-5 step's error."""
    size = (32, 1, 2, 1)
    g = torch.Generator().manual_seed(0)
    batch = {"state": torch.randn(16, 39, generator=g), "actions": torch.randn(16, 16, 4, generator=g)}
    variants = {"fd": ("finite_difference", None), "jvp": ("jvp", None),
                "one_call": (None, functools.partial(cost._fd_loss, one_call=True)),
                "two_calls": (None, functools.partial(cost._fd_loss, one_call=False)),
                "forward": (None, cost._forward_difference_loss)}
    losses = {}
    for name, (dudt, loss) in variants.items():
        policy = cost._policy("mean_flow", size, **({"meanflow_dudt": dudt} if dudt else {}))
        torch.manual_seed(5)
        losses[name] = (policy.compute_loss(batch).loss if loss is None else loss(policy, batch)).item()
    assert losses["one_call"] == pytest.approx(losses["fd"], rel=1e-5)
    assert losses["two_calls"] == pytest.approx(losses["fd"], rel=1e-6)
    assert losses["forward"] == pytest.approx(losses["jvp"], rel=1e-3)
    assert losses["fd"] == pytest.approx(losses["jvp"], rel=1e-4)


def test_timing_rows_are_finite_ratios_to_flow_matching(cost, monkeypatch):
    monkeypatch.setattr(cost, "BATCH", 8)
    res = cost.time_size("tiny", (32, 1, 2, 1), reps=1, warmup=0)
    names = [row["variant"] for row in res["rows"]]
    assert names == ["FM", "jvp", "finite_difference", "fd, one call (B + 2n rows)", "fd, two calls (B, then 2n rows)",
                     "forward difference (n rows)"]
    assert all(row["step_ms"] > 0 and 0 < row["vs_fm"] < float("inf") for row in res["rows"])
    assert "| tiny | finite_difference |" in cost.table([res])
    mixed = cost.time_size("tiny", (32, 1, 2, 1), reps=1, warmup=0, autocast=torch.bfloat16)
    assert "fd, one call (B + 2n rows)" not in [row["variant"] for row in mixed["rows"]]   # two calls under autocast
    assert "| tiny | bfloat16 | finite_difference |" in cost.table([mixed])


def test_quality_runs_train_the_multimodal_mean_flow_model_with_each_dudt(cost, tmp_path, monkeypatch):
    """`--quality-only` trains the multimodal benchmark's MeanFlow model (`--dudt` reaches its config),
    scores K = 1 and 2, and its held-out loss uses the exact JVP target whatever the model trained with."""
    from benchmarks import multimodal as mm
    made = []
    real = mm.make_policy
    monkeypatch.setattr(mm, "make_policy", lambda *a, **k: made.append(real(*a, **k)) or made[-1])
    monkeypatch.setattr(cost, "_heldout", functools.partial(cost._heldout, batches=1))
    rows = cost.quality([0], 2, methods=("finite_difference",), tiny=True, save_dir=str(tmp_path))
    assert [m.config.meanflow_dudt for m in made] == ["finite_difference"]
    assert all(m.config.flow_prediction == "sample" for m in made)              # the clean-chunk head
    assert [(r["dudt"], r["seed"]) for r in rows] == [("finite_difference", 0)]
    assert all(0 <= r[k]["on_mode"] <= 1 and r["heldout_loss"] > 0 for r in rows for k in ("K1", "K2"))
    saved = ActionDecoderPolicy.from_pretrained(tmp_path / "mf_finite_difference_seed0")
    assert saved.config.meanflow_dudt == "finite_difference"
    as_jvp = ActionDecoderPolicy.from_pretrained(tmp_path / "mf_finite_difference_seed0")
    as_jvp.config.meanflow_dudt = "jvp"
    assert cost._heldout(saved, mm) == cost._heldout(as_jvp, mm)
    assert "| 0 | finite_difference |" in cost.quality_table(rows)


def test_multimodal_dudt_option_reaches_the_mean_flow_config(cost, tmp_path):
    from benchmarks import multimodal as mm
    b = mm.Budget(hidden=32, layers=1, recipe={"dudt": "finite_difference"})
    assert mm.make_policy("mean_flow", 4, 4, b).config.meanflow_dudt == "finite_difference"
    assert mm.make_policy("flow_matching", 4, 4, b).config.meanflow_dudt == DecoderConfig().meanflow_dudt
    assert mm.main(["--tiny", "--only", "synthetic", "--decoders", "mean_flow", "--dudt", "jvp",
                    "--out", str(tmp_path)]) == 0
    assert json.loads((tmp_path / "multimodal_run.json").read_text())["meta"]["budget"]["recipe"] == {"dudt": "jvp"}


def test_ablation_script_sets_the_cli_trainings_dudt(monkeypatch):
    """`scripts/meanflow_norm_ablation.py cli --dudt M -- train ...` trains with meanflow_dudt=M."""
    import importlib.util
    import action_decoder.train as train_mod
    monkeypatch.setattr(train_mod, "decoder_config", train_mod.decoder_config)     # undone after the test
    spec = importlib.util.spec_from_file_location("ablation", ROOT / "scripts" / "meanflow_norm_ablation.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    cfg = train_mod.TrainConfig(decoder="mean_flow")
    for dudt in ("jvp", "finite_difference"):
        script.use_dudt(dudt)
        assert train_mod.decoder_config(cfg, 39, 4, ["push"]).meanflow_dudt == dudt


def test_bad_device_options_are_one_line_errors(cost, capsys):
    with pytest.raises(SystemExit):
        cost.main(["--autocast", "none,fp8", "--precision-only"])
    assert "--autocast: expected a comma-separated list of ['none', 'bf16'], got 'none,fp8'" in capsys.readouterr().err
    if not torch.cuda.is_available():
        with pytest.raises(SystemExit):
            cost.main(["--device", "cuda", "--precision-only"])
        assert "--device: expected a device this torch can use, got 'cuda'" in capsys.readouterr().err


def test_reported_median_and_quartiles_interpolate_between_order_statistics():
    import statistics

    from benchmarks.train_step_cost import _quantile

    for xs in ([4.0, 1.0, 3.0, 2.0], [float(x) for x in range(20)], [float(x) for x in range(9)]):
        assert _quantile(xs, 0.5) == statistics.median(xs)
        q1, _, q3 = statistics.quantiles(xs, n=4, method="inclusive")
        assert (_quantile(xs, 0.25), _quantile(xs, 0.75)) == (q1, q3)
