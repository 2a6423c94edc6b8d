"""Smoke test of the benchmark command (`python -m benchmarks --tiny`): not a timed test."""

import argparse
import json
import math
import os
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def bench_main(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))          # `benchmarks` lives at the repository root
    sys.modules.pop("benchmarks", None)
    from benchmarks.__main__ import main
    return main


def test_only_the_full_run_writes_the_committed_tables_unless_told(bench_main, monkeypatch):
    import benchmarks.suite as suite

    seen = []
    monkeypatch.setattr(suite, "run_suite", seen.append)
    for argv in (["--quick"], ["--tiny"], [], ["--quick", "--out", "docs/benchmarks"]):
        assert bench_main(argv) == 0
    assert [c.out for c in seen] == ["outputs/benchmarks-quick", "outputs/benchmarks-quick", "docs/benchmarks",
                                     "docs/benchmarks"]


def test_quick_mode_on_a_tiny_config_writes_finite_tables(bench_main, tmp_path, monkeypatch):
    pytest.importorskip("diffusers")
    pytest.importorskip("matplotlib")
    quality = tmp_path / "evals"
    quality.mkdir()
    (quality / "eval.json").write_text(json.dumps(
        {"decoder_type": "mean_flow", "sampler": "ode", "steps": 1, "success_rate": 0.5, "latency_ms": 3.0}))
    monkeypatch.chdir(tmp_path)                      # a checkout: docs/benchmarks holds the committed tables
    (tmp_path / "docs" / "benchmarks").mkdir(parents=True)
    assert bench_main(["--tiny", "--quality-dir", str(quality)]) == 0
    assert not any((tmp_path / "docs" / "benchmarks").iterdir()), "a smoke run leaves the committed tables alone"
    out = tmp_path / "outputs" / "benchmarks-quick"

    readme = (out / "README.md").read_text()
    for heading in ("## Machine", "## 1. Sampler overhead", "## 2. Training step", "## 3. Peers",
                    "## 4. Quality vs latency", "## 5. Memory"):
        assert heading in readme
    assert "torch thread" in readme and "not measured" in readme
    assert (out / "benchmarks.png").stat().st_size > 0

    res = json.loads((out / "results.json").read_text())
    ratios = [r["overhead"] for s in res["sampling"] for r in s["rows"]]
    ratios += [r["vs_fm"] for s in res["training"] for r in s["rows"]]
    ratios += [r["ours_over_peer"] for s in res["peers"] for r in s["rows"]]
    ratios += [v for s in res["training"] for v in s["memory"]["bytes"].values()]
    assert ratios and all(math.isfinite(x) and x > 0 for x in ratios)
    assert all(r["agree"] for s in res["peers"] for r in s["rows"])      # same outputs as the peers
    mf1 = [r for r in res["quality"]["rows"] if (r["decoder"], r["sampler"], r["steps"]) == ("mean_flow", "ode", 1)]
    assert mf1[0]["success_rate"] == 0.5 and mf1[0]["latency_ms"] == 3.0

    # Regenerating keeps hand-written text outside the generated block.
    (out / "README.md").write_text(readme + "\nHAND-WRITTEN NOTE\n")
    assert bench_main(["--tiny", "--out", str(out), "--sections", "quality", "--no-plot"]) == 0
    again = (out / "README.md").read_text()
    assert "HAND-WRITTEN NOTE" in again and "## 4. Quality vs latency" in again


def test_mlp_reference_writes_a_column_the_bc_table_reads(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    monkeypatch.setenv("ACTION_DECODER_CACHE", str(tmp_path / "cache"))
    for name in [m for m in sys.modules if m == "benchmarks" or m.startswith("benchmarks.")]:
        sys.modules.pop(name)
    from benchmarks import metaworld_bc, mlp_baseline, scripted_expert

    # The ceiling column: the demonstrator on the same layouts (reach's expert never misses).
    args = type("Args", (), {"runs": str(tmp_path / "expert_runs"), "demo_noise": 0.3, "done": {}, "episodes": 2,
                             "results": tmp_path / "bc.json"})
    monkeypatch.setattr(metaworld_bc, "_run", lambda cmd, log: scripted_expert.main(cmd[3:]))
    metaworld_bc.run_one("metaworld/reach-v3", 0, "scripted_expert", args)
    (row,) = json.loads((tmp_path / "bc.json").read_text())
    assert (row["decoder"], row["sampler"], row["steps"], row["success"]) == ("scripted_expert", "expert", 1, 1.0)
    assert metaworld_bc.matching([row], {"demos": 10, "demo_noise": 0.3}) == [row], "no demonstrations: any recipe"
    assert (tmp_path / "expert_runs" / "reach-v3_s0_scripted_expert" / "eval_expert.json").is_file()

    res = mlp_baseline.run("metaworld/reach", seed=0, demos=2, steps=20, batch_size=8, episodes=2, ks=(2, 1))
    assert 150_000 < res["params"] < 200_000            # the ~190k-parameter reference of the issue
    mlp_baseline.write_evals(res, tmp_path / "runs" / "reach-v3_s0_mlp_baseline", (2, 1))
    rows = metaworld_bc.collect(tmp_path / "runs")
    assert {(r["steps"], r["success"], r["state_layout"], r["augment_shift"]) for r in rows} == {
        (2, res["success_k2"], "metaworld", 0.05), (1, res["success_k1"], "metaworld", 0.05)}
    want = {"demos": 2, "train_steps": 1500, "episodes": 2, "state_layout": "metaworld", "augment_shift": 0.05,
            "n_action_steps": 4}
    assert len(metaworld_bc.matching(rows, want)) == 2, "the MLP's own budget and re-planning match any decoder's"
    (run := tmp_path / "runs" / "reach-v3_s1_mlp_baseline").mkdir()    # written before demo noise existed
    old = json.loads((tmp_path / "runs" / "reach-v3_s0_mlp_baseline" / "eval_ode_k1.json").read_text())
    del old["recipe"]["demo_noise"]
    (run / "eval_ode_k1.json").write_text(json.dumps({**old, "seed": 1}))
    (seed1,) = [r for r in metaworld_bc.collect(tmp_path / "runs") if r["seed"] == 1]
    assert seed1["demo_noise"] == 0.0, "a run recorded before demo noise existed had clean demonstrations"
    shutil.rmtree(run)

    # A multi-task policy's evaluation contributes one row per task.
    mt = tmp_path / "runs" / "MT10_s0_flow_matching"
    mt.mkdir()
    (mt / "eval_ode_k10.json").write_text(json.dumps(
        {"decoder_type": "flow_matching", "sampler": "ode", "steps": 10, "success_rate": 0.55, "seed": 0,
         "per_task": {"reach-v3": 0.9, "push-v3": 0.2}, "recipe": {"demos": 2, "train_steps": 20}}))
    table = metaworld_bc.tabulate(metaworld_bc.collect(tmp_path / "runs"))
    assert table["push-v3"] == {("flow_matching", "ode", 10): {0: 0.2}}
    assert table["reach-v3"][("flow_matching", "ode", 10)] == {0: 0.9}
    assert table["reach-v3"][("mlp_baseline", "ode", 1)] == {0: res["success_k1"]}


def test_bc_results_persist_across_invocations_and_the_table_keeps_one_recipe(monkeypatch, tmp_path):
    from benchmarks import metaworld_bc

    def row(task, seed, success, train_steps=1500, demo_noise=0.0, n_action_steps=8, batch_size=128):
        return {"task": task, "seed": seed, "decoder": "mean_flow", "sampler": "ode", "steps": 1, "episodes": 50,
                "demos": 10, "demo_noise": demo_noise, "train_steps": train_steps, "batch_size": batch_size,
                "state_layout": "metaworld", "augment_shift": 0.05, "n_action_steps": n_action_steps,
                "success": success}

    results = tmp_path / "bc.json"
    unbatched = {k: v for k, v in row("push-v3", 1, 0.7).items() if k != "batch_size"}    # written before batch_size was part of a row
    metaworld_bc.merge(results, [row("push-v3", 0, 0.5), unbatched, row("push-v3", 0, 0.1, 5000),
                                 row("push-v3", 0, 0.2, demo_noise=0.3), row("push-v3", 0, 0.6, n_action_steps=4)])
    merged = metaworld_bc.merge(results, [row("push-v3", 0, 0.9), row("hammer-v3", 0, 0.3),   # a later invocation
                                          row("push-v3", 1, 0.4, batch_size=256)])
    assert len(merged) == 7 and len(results.read_text().splitlines()) == 9     # one row per line
    want = {"demos": 10, "demo_noise": 0.0, "train_steps": 1500, "batch_size": 128, "episodes": 50,
            "state_layout": "metaworld", "augment_shift": 0.05, "n_action_steps": 8}
    table = metaworld_bc.tabulate(metaworld_bc.matching(merged, want))
    assert table == {"push-v3": {("mean_flow", "ode", 1): {0: 0.9, 1: 0.7}}, "hammer-v3": {("mean_flow", "ode", 1): {0: 0.3}}}
    big = metaworld_bc.tabulate(metaworld_bc.matching(merged, {**want, "batch_size": 256}))
    assert big == {"push-v3": {("mean_flow", "ode", 1): {1: 0.4}}}, "a row without a batch was trained with 128"
    noisy = metaworld_bc.tabulate(metaworld_bc.matching(merged, {**want, "demo_noise": 0.3}))
    assert noisy == {"push-v3": {("mean_flow", "ode", 1): {0: 0.2}}}
    replanned = metaworld_bc.tabulate(metaworld_bc.matching(merged, {**want, "n_action_steps": 4}))
    assert replanned == {"push-v3": {("mean_flow", "ode", 1): {0: 0.6}}}
    # MeanFlow rows written before `meanflow_target` existed trained with the identity; a split row is kept apart.
    assert {r["meanflow_target"] for r in merged} == {"identity"}
    merged = metaworld_bc.merge(results, [{**row("push-v3", 0, 0.95), "meanflow_target": "split"}])
    split = metaworld_bc.tabulate(metaworld_bc.matching(merged, {**want, "meanflow_target": "split"}))
    assert split == {"push-v3": {("mean_flow", "ode", 1): {0: 0.95}}}
    assert metaworld_bc.tabulate(metaworld_bc.matching(merged, {**want, "meanflow_target": "identity"})) == table

    # A run whose rows a results file already holds is not trained again.
    args = type("Args", (), {"runs": str(tmp_path / "runs"), "demo_noise": 0.0, "steps": 5000, "batch_size": 128,
                             "done": {("metaworld/push-v3", 0): {("mean_flow", "ode", 1), ("mean_flow", "ode", 2)}}})
    metaworld_bc.run_one("metaworld/push-v3", 0, "mean_flow", args)      # would need demos and minutes
    assert not (tmp_path / "runs").exists()

    # A finished run's rows reach the results file as soon as the run ends, before the grid does.
    run = tmp_path / "runs" / "hammer-v3_s0_mean_flow"
    (run / "final").mkdir(parents=True)
    (run / "final" / "model.safetensors").touch()
    for k, success in ((1, 0.25), (2, 0.75)):
        (run / f"eval_ode_k{k}_n8.json").write_text(json.dumps(
            {"decoder_type": "mean_flow", "sampler": "ode", "steps": k, "seed": 0, "episodes_per_task": 50,
             "n_action_steps": 8, "per_task": {"hammer-v3": success},
             "recipe": {"demos": 10, "demo_noise": 0.0, "train_steps": 1500, "state_layout": "metaworld",
                        "augment_shift": 0.05}}))
    args = type("Args", (), {"runs": str(tmp_path / "runs"), "demo_noise": 0.0, "done": {}, "results": results,
                             "n_action_steps": 8, "episodes": 50, "steps": 5000, "batch_size": 128,
                             "meanflow_target": "identity"})
    metaworld_bc.run_one("metaworld/hammer-v3", 0, "mean_flow", args)
    kept = [r for r in json.loads(results.read_text()) if r["task"] == "hammer-v3" and r["train_steps"] == 1500]
    assert sorted((r["steps"], r["success"]) for r in kept) == [(1, 0.25), (2, 0.75)], "the fresh row replaces 0.3"

    # Another number of executed actions re-evaluates the trained policy under its own file name.
    calls = []
    monkeypatch.setattr(metaworld_bc, "_run", lambda cmd, log: calls.append(cmd))
    args.n_action_steps = 4
    metaworld_bc.run_one("metaworld/hammer-v3", 0, "mean_flow", args)
    assert [c[c.index("--output") + 1].rsplit("/", 1)[-1] for c in calls] == ["eval_ode_k1_n4.json", "eval_ode_k2_n4.json"]
    assert all(c[3] == "eval" and c[c.index("--n-action-steps") + 1] == "4" for c in calls), "no retraining"

    # Another batch trains a policy of its own, beside the runs made with 128.
    calls.clear()
    args.steps, args.batch_size, args.demos = 2500, 256, 10
    metaworld_bc.run_one("metaworld/hammer-v3", 0, "mean_flow", args)
    train_cmd = calls[0]
    assert train_cmd[3] == "train" and train_cmd[train_cmd.index("--batch-size") + 1] == "256"
    assert train_cmd[train_cmd.index("--output-dir") + 1].endswith("hammer-v3_s0_2500x256_mean_flow")

    # The table is rebuilt; what was written below it by hand stays.
    args = type("Args", (), {"demos": 10, "demo_noise": 0.0, "steps": 1500, "batch_size": 128, "episodes": 50,
                             "n_action_steps": 8})
    md = tmp_path / "bc.md"
    metaworld_bc.write_table(table, md, args, results)
    md.write_text(md.read_text() + "What the table says.\n")
    text = metaworld_bc.write_table({"push-v3": {("mean_flow", "ode", 1): {0: 0.5}}}, md, args, results)
    assert "| push-v3 | 50 (1) |" in text and "hammer" not in md.read_text()
    text = metaworld_bc.write_table({"push-v3": {("mean_flow", "ode", 1): {0: 0.5, 1: 0.9},
                                                 ("flow_matching", "ode", 1): {0: 1.0}},
                                     "hammer-v3": {("mean_flow", "ode", 1): {0: 0.1}}}, md, args, results)
    assert "| push-v3 | 100 (1) | 70 ± 28 (2) |" in text, "a cell: every seed of its column"
    assert "| **mean (1 tasks, 1 (task, seed) runs with every column)** | **100.0** | **50.0** |" in text, \
        "the mean: hammer lacks FM, and FM lacks push's seed 1"
    assert "| mean of task means, each column's own seeds (1 tasks) | 100.0 | 70.0 |" in text
    assert md.read_text().endswith(metaworld_bc.NOTES + "\nWhat the table says.\n")


def test_rl_table_measures_the_gain_with_one_sampler_at_the_fine_tunings_k(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    run = tmp_path / "runs" / "reach-v3_mean_flow"
    (run / "ft").mkdir(parents=True)

    def ev(name, rate, steps):
        (run / name).write_text(json.dumps({"decoder_type": "mean_flow", "success_rate": rate, "steps": steps}))

    ev("bc_eval.json", 0.30, 1)          # MeanFlow's default K = 1
    ev("bc_eval_k10.json", 0.40, 10)     # the K the fine-tuned policy samples with
    ev("ft_eval_sde.json", 0.70, 10)
    ev("ft_eval_ode.json", 0.60, 10)
    hist = [{"iteration": 1, "env_steps": 6400, "wall_s": 60.0, "cpu_s": 55.0, "success": 0.75, "kl_bc": 2.5}]
    (run / "ft" / "finetune_log.json").write_text(json.dumps(
        {"task": "reach-v3", "config": {"algo": "ppo", "sigma": 0.25}, "history": hist,
         "evals": [{"iteration": 1, "env_steps": 6400, "success_sde": 0.5, "success_ode": 0.5}]}))
    rows = rl_finetune.collect(tmp_path / "runs")
    args = argparse.Namespace(episodes=50, demos=3, bc_steps=2000, results="r.json")
    text = rl_finetune.write_report(rows, tmp_path / "t.md", tmp_path / "t.png", args)
    # the ODE at K = 10 on both sides: 60 − 40, whatever the SDE or BC's own K gave; training success 75
    assert "| mean_flow | ppo, a = 0.25 | 0 | 30 (K=1) | 40 (K=10) | 70 | 60 | +20 | 75 | 2.5 |" in text
    assert rows[0]["curve"] == [[0.92, 0.5, 0.5, 6400]]             # 55 CPU-s
    md = tmp_path / "t.md"
    md.write_text(md.read_text() + "What the table says.\n")
    rl_finetune.write_report(rows[:0], md, tmp_path / "t.png", args)   # rebuilt: the table changes, the notes stay
    assert "reach-v3" not in md.read_text() and md.read_text().endswith(rl_finetune.NOTES + "\nWhat the table says.\n")


def test_rl_rows_of_a_smaller_env_budget_stay_beside_the_protocols(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    def row(budget, ft_ode):
        return {"task": "reach-v3", "decoder": "mean_flow", "algo": "dsrl", "env_budget": budget, "bc": 0.2,
                "bc_steps": 1, "bc_at_ft_k": 0.2, "ft_k": 1, "ft_sde": None, "ft_ode": ft_ode, "cpu_min": 20.0,
                "env_steps": budget + 800, "measured": "2026-11-28", "curve": []}

    results = tmp_path / "rl.json"
    rl_finetune.merge(results, [row(100_000, 0.5)])
    merged = rl_finetune.merge(results, [row(rl_finetune.ENV_STEPS["dsrl"], 0.7)])   # the same run, continued
    assert [r["ft_ode"] for r in merged] == [0.5, 0.7]
    text = rl_finetune.write_report(merged, tmp_path / "t.md", tmp_path / "t.png",
                                    argparse.Namespace(episodes=50, demos=3, bc_steps=2000, results="r.json"))
    assert "- dev half, mean_flow (dsrl, env_steps=100000): mean gain +30.0 points" in text
    assert "- dev half, mean_flow (dsrl): mean gain +50.0 points" in text


def test_rl_harness_continues_a_run_of_a_smaller_env_budget_and_evaluates_it_again(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    args = argparse.Namespace(runs=str(tmp_path / "runs"), algo="dsrl", demos=3, bc_steps=2000, episodes=50,
                              cpu_minutes=45.0, finetune_args=[])
    run = rl_finetune.run_dir("metaworld/reach", "mean_flow", args)
    ft = run / "ft"
    for d in (run / "bc" / "final", ft / "final", ft / "checkpoints"):
        d.mkdir(parents=True)
    (ft / "checkpoints" / "last").write_text("step_0000063")
    (run / "bc" / "final" / "model.safetensors").write_text("w")
    (run / "bc_eval.json").write_text(json.dumps({"steps": 1, "success_rate": 0.2}))
    (ft / "finetune_log.json").write_text(json.dumps({"config": {"env_steps": 100_000, "max_cpu_minutes": 45.0}}))
    evaluation = run / "ft_eval_ode.json"
    evaluation.write_text("{}")
    os.utime(evaluation, (1, 1))
    (ft / "final" / "model.safetensors").write_text("w")              # newer than the evaluation: it is stale
    calls = []
    monkeypatch.setattr(rl_finetune, "_run", lambda cmd, log: calls.append(cmd))
    rl_finetune.run_one("metaworld/reach", "mean_flow", 0, args)
    finetune = next(c for c in calls if "finetune" in c)
    assert finetune[finetune.index("--env-steps") + 1] == str(rl_finetune.ENV_STEPS["dsrl"]) and "--resume" in finetune
    assert any("eval" in c and str(evaluation) in c for c in calls), "the continued weights are evaluated again"
    calls.clear()
    (ft / "finetune_log.json").write_text(json.dumps({"config": {"env_steps": 200_000, "max_cpu_minutes": 45.0}}))
    evaluation.write_text("{}")                                          # fresh: nothing to run
    rl_finetune.run_one("metaworld/reach", "mean_flow", 0, args)
    assert calls == []


def test_rl_results_keep_earlier_rows_and_take_fresh_ones(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    def row(task, ft_sde):
        return {"task": task, "decoder": "flow_matching", "algo": "ppo", "bc": 0.2, "bc_steps": 10, "bc_at_ft_k": 0.2,
                "ft_k": 10, "ft_sde": ft_sde, "ft_ode": 0.1, "cpu_min": 45.0, "env_steps": 1000, "measured": "2026-11-23",
                "curve": []}

    results = tmp_path / "docs" / "rl.json"
    rl_finetune.merge(results, [row("reach-v3", 0.5), row("push-v3", 0.3)])
    merged = rl_finetune.merge(results, [row("reach-v3", 0.9)])          # a new run of reach only
    assert [(r["task"], r["ft_sde"]) for r in merged] == [("push-v3", 0.3), ("reach-v3", 0.9)]
    assert json.loads(results.read_text()) == merged
    text = rl_finetune.write_report(merged, tmp_path / "t.md", tmp_path / "t.png",
                                    argparse.Namespace(episodes=50, demos=3, bc_steps=2000, results="r.json"))
    assert "| dev | push-v3 | flow_matching | ppo | 0 | 20 (K=10) | 20 (K=10) | 30 | 10 | -10 | – | – | 45 | 1000 | " \
        "2026-11-23 |" in text                                         # a row from before the training-success column
    assert "- dev half, flow_matching (ppo): mean gain -10.0 points over 2 task(s) (seed 0)" in text
    assert not (tmp_path / "t.png").exists()                            # no curves kept: no plot
    changed = dict(row("reach-v3", 0.7), recipe="lr_schedule=adaptive", sigma=0.25)   # one option changed
    merged = rl_finetune.merge(results, [changed])
    assert [(r["task"], r["ft_sde"]) for r in merged] == [("push-v3", 0.3), ("reach-v3", 0.9), ("reach-v3", 0.7)]
    text = rl_finetune.write_report(merged, tmp_path / "t.md", tmp_path / "t.png",
                                    argparse.Namespace(episodes=50, demos=3, bc_steps=2000, results="r.json"))
    assert "| dev | reach-v3 | flow_matching | ppo, a = 0.25, lr_schedule=adaptive | 0 |" in text
    assert "- dev half, flow_matching (ppo, a = 0.25, lr_schedule=adaptive): mean gain -10.0 points over 1 task(s)" in text
    assert "- dev half, flow_matching (ppo): mean gain -10.0 points over 2 task(s) (seed 0)" in text


def test_rl_recipe_names_the_options_a_run_changed(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    run_only = {"seed": 3, "max_cpu_minutes": 45.0, "sigma": 0.5, "output_dir": "x", "eval_every": 10}
    assert rl_finetune.recipe({}) == rl_finetune.recipe(run_only) == "defaults"
    assert rl_finetune.recipe({**run_only, "lr": 1e-4, "lr_schedule": "fixed"}) == "defaults"     # set to the default
    assert rl_finetune.recipe({"lr_schedule": "adaptive", "kl_coef": 0.01, "lr": 1e-4}) == \
        "kl_coef=0.01, lr_schedule=adaptive"
    # the critic's warm-up is part of a recipe only where the critic acts (group size 1); None means 1
    for warmup in (None, 1, 5):
        assert rl_finetune.recipe({"critic_warmup_iters": warmup, "group_size": 4}) == "defaults"
    assert rl_finetune.recipe({"critic_warmup_iters": None, "group_size": 1}) == \
        rl_finetune.recipe({"critic_warmup_iters": 1, "group_size": 1}) == "group_size=1"
    assert rl_finetune.recipe({"critic_warmup_iters": 3, "group_size": 1}) == "critic_warmup_iters=3, group_size=1"
    # DSRL plays one episode a layout and warms up for 0 iterations by default
    assert rl_finetune.recipe({"algo": "dsrl", "critic_warmup_iters": None}) == \
        rl_finetune.recipe({"algo": "dsrl", "critic_warmup_iters": 0}) == "defaults"
    assert rl_finetune.recipe({"algo": "dsrl", "critic_warmup_iters": 1}) == "critic_warmup_iters=1"
    # the reward: dense for PPO, success for DSRL, whether logged as None or spelt out
    assert rl_finetune.recipe({"reward": "dense"}) == rl_finetune.recipe({"reward": None}) == "defaults"
    assert rl_finetune.recipe({"algo": "dsrl", "reward": "success"}) == "defaults"
    assert rl_finetune.recipe({"algo": "dsrl", "reward": "dense"}) == "reward=dense"
    assert rl_finetune.recipe({"reward": "success"}) == "reward=success"
    assert rl_finetune.ft_dir_name(["--reward", "dense"], 1, "dsrl") == "ft_reward-dense_s1"


def test_rl_early_phase_reads_the_first_iterations_of_a_run(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    # 25 iterations: single updates up to iteration 6, KL to BC = iteration / 2, success 0.5 then 0.1
    hist = [{"iteration": i, "epochs": 1 if i <= 6 else 3, "kl_bc": i / 2, "success": 0.5 if i <= 10 else 0.1,
             "approx_kl": 0.3, "decisions": 800} for i in range(1, 26)]
    e = rl_finetune.early_phase(hist, 512)
    assert e == {"first_update_kl": 0.6, "one_update_iters": 6, "kl_bc_it10": 5.0, "kl_bc_it20": 10.0,
                 "train_success_it1_10": 0.5, "train_success_it11_20": 0.1}
    # logged directly where the log has it; not derivable from one minibatch per epoch, nor from a short run
    assert rl_finetune.early_phase([{**hist[0], "approx_kl_first_update": 0.41}] + hist[1:], 512)["first_update_kl"] == 0.41
    short = rl_finetune.early_phase(hist[:8], 1024)
    assert short["first_update_kl"] is None and short["kl_bc_it20"] is None and short["train_success_it11_20"] is None
    row = {"task": "reach-v3", "decoder": "flow_matching", "algo": "ppo", "bc": 0.2, "bc_steps": 10, "bc_at_ft_k": 0.2,
           "ft_k": 10, "ft_sde": 0.5, "ft_ode": 0.1, "cpu_min": 45.0, "env_steps": 1000, "measured": "2026-11-26",
           "curve": [], "early": e}
    text = rl_finetune.write_report([row], tmp_path / "t.md", tmp_path / "t.png",
                                    argparse.Namespace(episodes=50, demos=3, bc_steps=2000, results="r.json"))
    assert "| dev | reach-v3 | flow_matching | defaults | 0 | 0.6 | 6 | 5.0 / 10.0 | 0.50 / 0.10 | -10 |" in text
    # logs with the update count: it decides, whatever the epochs and minibatches
    counted = [{**h, "updates": 1 if h["iteration"] in (2, 3) else 2, "epochs": 2} for h in hist]
    assert rl_finetune.early_phase(counted, 1024)["one_update_iters"] == 2


def test_rl_task_set_comes_from_the_band_and_a_fixed_split(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    bc = {"reach-v3": 0.30, "push-back-v3": 0.40, "handle-pull-v3": 0.15, "lever-pull-v3": 0.65,
          "coffee-push-v3": 0.32, "door-open-v3": 0.90, "pick-place-v3": 0.14, "peg-unplug-side-v3": 0.66}
    chosen = rl_finetune.split(bc)
    assert chosen["bc"] == dict(sorted(bc.items())) and chosen["band"] == [0.15, 0.65]
    # in band, edges included; reach is a task the defaults were tuned on, so dev whatever its hash
    assert sorted(chosen["dev"] + chosen["report"]) == ["coffee-push-v3", "handle-pull-v3", "lever-pull-v3",
                                                        "push-back-v3", "reach-v3"]
    assert "reach-v3" in chosen["dev"] and rl_finetune.half("reach-v3") == "dev"
    assert chosen["report"] == ["handle-pull-v3", "lever-pull-v3", "push-back-v3"]   # sha256 parity, fixed
    assert chosen["dev"] == ["coffee-push-v3", "reach-v3"]
    path = tmp_path / "rl_tasks.json"
    path.write_text(json.dumps(chosen))
    assert rl_finetune.resolve_task_spec("report", path) == chosen["report"]
    assert rl_finetune.resolve_task_spec("metaworld/reach", path) == ["reach-v3"]
    with pytest.raises(SystemExit, match=r"--tasks dev: expected the task set .*missing.json \(run --select first\)"):
        rl_finetune.resolve_task_spec("dev", tmp_path / "missing.json")
    text = rl_finetune.task_set_text(chosen, argparse.Namespace(task_set="rl_tasks.json", episodes=50))
    assert "15–65 % of 50 evaluation episodes, seed 0 — 5 of 8 tasks" in text
    assert "| reach-v3 | 30 | dev |" in text and "| lever-pull-v3 | 65 | report |" in text
    assert "Below the band (1): pick-place-v3 14. Above it (2): door-open-v3 90, peg-unplug-side-v3 66." in text


def test_rl_select_writes_the_task_set_from_every_tasks_bc_run(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune
    import action_decoder.envs.metaworld_tasks as mw

    rates = {"reach-v3": 0.3, "door-open-v3": 0.9, "lever-pull-v3": 0.2}
    monkeypatch.setattr(mw, "all_tasks", lambda: list(rates))

    def fake_bc(task, decoder, args):
        assert decoder == "flow_matching" and task.startswith("metaworld/")
        run = tmp_path / "runs" / task.split("/")[1]
        run.mkdir(parents=True)
        (run / "bc_eval.json").write_text(json.dumps({"success_rate": rates[task.split("/")[1]]}))
        return run

    monkeypatch.setattr(rl_finetune, "train_bc", fake_bc)
    out = tmp_path / "docs" / "rl_tasks.json"
    rl_finetune.main(["--select", "--task-set", str(out), "--runs", str(tmp_path / "runs")])
    chosen = json.loads(out.read_text())
    assert chosen["bc"] == dict(sorted(rates.items()))
    assert chosen["dev"] == ["reach-v3"] and chosen["report"] == ["lever-pull-v3"]


def test_rl_rows_keep_each_fine_tuning_seed_and_report_their_spread(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    run = tmp_path / "runs" / "reach-v3_flow_matching"
    for suffix, seed, rate in (("", 0, 0.5), ("_s1", 1, 0.3)):
        (run / f"ft{suffix}").mkdir(parents=True)
        for name, r in (("ft_eval_sde", rate), ("ft_eval_ode", rate - 0.1)):
            (run / f"{name}{suffix}.json").write_text(json.dumps({"success_rate": r, "steps": 10}))
        hist = [{"iteration": i, "env_steps": 800 * i, "wall_s": 1.0, "cpu_s": 60.0 * i, "success": i / 20, "kl_bc": 1.0}
                for i in range(1, 13)]
        evals = [{"iteration": 0, "env_steps": 0, "success_ode": 0.2},
                 {"iteration": 10, "env_steps": 8000, "success_ode": 0.5 if seed == 0 else 0.3},
                 {"iteration": 12, "env_steps": 9600, "success_ode": 0.1}][: 3 if seed else 2]
        (run / f"ft{suffix}" / "finetune_log.json").write_text(json.dumps(
            {"task": "reach-v3", "config": {"algo": "ppo", "seed": seed}, "history": hist, "evals": evals}))
    (run / "bc_eval.json").write_text(json.dumps({"decoder_type": "flow_matching", "success_rate": 0.2, "steps": 10}))
    (run / "ft_s2").mkdir()                                  # a fine-tuning still running: no row yet
    rows = rl_finetune.collect(tmp_path / "runs")
    assert [(r["seed"], r["ft_sde"], r["half"]) for r in rows] == [(0, 0.5, "dev"), (1, 0.3, "dev")]
    assert rows[0]["train_success_last10"] == round(sum(i / 20 for i in range(3, 13)) / 10, 3)   # the last 10
    merged = rl_finetune.merge(tmp_path / "r.json", rows)
    assert len(merged) == 2                                  # seeds are kept apart
    lines = rl_finetune.summary(merged)
    # at 8000 env steps the seeds' latest gains are +30 and +10 (mean +20 ≥ +15); at 0 both are 0
    assert lines == ["- dev half, flow_matching (ppo): mean gain +20.0 points over 1 task(s) (seed 0)",
                     "- dev half, flow_matching (ppo), every seed: mean gain +10.0 points over 2 run(s); 0 end more "
                     "than 5 points below BC; the seeds of 1 of 1 task(s) within 20 points; mean gain +15 first "
                     "reached at 8000 env steps",
                     "- noise: reach-v3 flow_matching (ppo) gains over fine-tuning seeds: +20, +0 (range 20 points)"]
    assert rl_finetune.steps_to_mean_gain(merged, mark=25) is None     # +30 and −10 at 9600: never +25 together


def test_rl_summary_counts_agreeing_seeds_and_compares_algorithms_in_env_steps(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    def row(task, algo, seed, curve, final):     # curve: (env steps, ODE success) of each evaluation
        return {"task": task, "decoder": "mean_flow", "algo": algo, "sigma": None, "recipe": "defaults", "seed": seed,
                "bc_at_ft_k": 0.2, "ft_ode": final, "env_steps": curve[-1][0],
                "curve": [[i, None, ok, x] for i, (x, ok) in enumerate(curve)]}

    rows = [row("lever-pull-v3", "dsrl", 0, [(0, 0.2), (16000, 0.5), (100000, 0.6)], 0.6),
            row("lever-pull-v3", "dsrl", 1, [(0, 0.2), (16000, 0.3), (100000, 0.3)], 0.3),   # 30 points apart
            row("soccer-v3", "dsrl", 0, [(0, 0.2), (16000, 0.4), (100000, 0.5)], 0.5),
            row("soccer-v3", "dsrl", 1, [(0, 0.2), (16000, 0.4), (100000, 0.45)], 0.45),
            row("lever-pull-v3", "ppo", 0, [(0, 0.2), (320000, 0.3), (600000, 0.3)], 0.3),
            row("soccer-v3", "ppo", 0, [(0, 0.2), (320000, 0.3), (600000, 0.35)], 0.35)]
    lines = rl_finetune.summary(rows)
    dsrl = next(ln for ln in lines if "(dsrl), every seed" in ln)
    assert "the seeds of 1 of 2 task(s) within 20 points" in dsrl
    assert "first reached at 16000 env steps" in dsrl          # mean of +30, +10, +20, +20 = +20 at 16k
    assert "- report half, mean_flow, defaults over the 2 task(s) both ran: env steps to a mean gain of +15: " \
           "dsrl 16000; ppo never within 600000 (37.5× or more)" in lines
    one_ppo = [r for r in rows if not (r["algo"] == "ppo" and r["task"] == "soccer-v3")]
    assert "- report half, mean_flow, defaults over the 1 task(s) both ran: env steps to a mean gain of +15: " \
           "dsrl 16000; ppo never within 600000 (37.5× or more)" in rl_finetune.summary(one_ppo)   # lever-pull: +30, +10
    ppo_first = [dict(r, curve=[[0, None, 0.2, 0], [1, None, 0.6, 32000]]) if r["algo"] == "ppo" else r for r in rows]
    assert "- report half, mean_flow, defaults over the 2 task(s) both ran: env steps to a mean gain of +15: " \
           "dsrl 16000; ppo 32000 (2.0×)" in rl_finetune.summary(ppo_first)
    tuned = [dict(r, recipe="lr=1e-3") if r["algo"] == "ppo" else r for r in rows]     # not the defaults: no comparison
    assert not any("both ran" in ln for ln in rl_finetune.summary(tuned))


def test_sde_exploration_splits_the_variance_of_executed_actions(monkeypatch, tmp_path, capsys):
    monkeypatch.syspath_prepend(str(ROOT))
    import torch

    from action_decoder import ActionDecoderPolicy, DecoderConfig
    from benchmarks.sde_exploration import main

    cfg = DecoderConfig(decoder_type="flow_matching", state_dim=39, action_dim=4, action_chunk_size=4, n_action_steps=2,
                        hidden_size=16, num_hidden_layers=1, num_attention_heads=2, num_key_value_heads=1,
                        extra={"tasks": ["reach-v3"]})
    torch.manual_seed(0)
    ActionDecoderPolicy(cfg).save_pretrained(tmp_path / "p")
    assert main(["--checkpoint", str(tmp_path / "p"), "--layouts", "2", "--samples", "4", "--steps", "4"]) == 0
    rows = [line.split("|")[2:-1] for line in capsys.readouterr().out.splitlines() if line.startswith("| explore")
            or line.startswith("| fixed")]
    assert len(rows) == 4
    for all_steps, first, last, last1 in [[float(x) for x in r] for r in rows]:
        assert all_steps > 0 and 0 <= first < all_steps and last1 <= last * 1.5 + 1e-6


def test_bc_grid_trains_meanflow_with_the_requested_target_in_its_own_run_directory(monkeypatch, tmp_path):
    from benchmarks import metaworld_bc

    calls = []
    monkeypatch.setattr(metaworld_bc, "_run", lambda cmd, log: calls.append(cmd))
    monkeypatch.setattr(metaworld_bc, "_keep", lambda run, args: None)
    args = type("Args", (), {"runs": str(tmp_path / "runs"), "demo_noise": 0.0, "done": {}, "n_action_steps": 4,
                             "episodes": 50, "steps": 5000, "batch_size": 128, "demos": 10, "meanflow_target": "split"})
    metaworld_bc.run_one("metaworld/push-v3", 0, "mean_flow", args)
    train = calls[0]
    assert train[train.index("--meanflow-target") + 1] == "split"
    assert train[train.index("--output-dir") + 1].endswith("push-v3_s0_split_mean_flow")
    calls.clear()
    metaworld_bc.run_one("metaworld/push-v3", 0, "flow_matching", args)     # the field is MeanFlow's alone
    assert "--meanflow-target" not in calls[0] and calls[0][calls[0].index("--output-dir") + 1].endswith("s0_flow_matching")


def test_bc_table_of_a_meanflow_target_shows_the_tasks_it_was_measured_on(tmp_path):
    from benchmarks import metaworld_bc

    def row(task, decoder, steps, success, **kw):
        return {"task": task, "seed": 0, "decoder": decoder, "sampler": "ode", "steps": steps, "episodes": 50,
                "demos": 10, "demo_noise": 0.0, "train_steps": 5000, "batch_size": 128, "state_layout": "metaworld",
                "augment_shift": 0.05, "n_action_steps": 4, "success": success, **kw}

    results, table = tmp_path / "bc.json", tmp_path / "split.md"
    metaworld_bc.merge(results, [row("push-v3", "flow_matching", 10, 0.9), row("hammer-v3", "flow_matching", 10, 0.8),
                                 row("push-v3", "mean_flow", 1, 0.7), row("hammer-v3", "mean_flow", 1, 0.6),
                                 row("push-v3", "mean_flow", 1, 0.75, meanflow_target="split")])
    metaworld_bc.main(["--report-only", "--meanflow-target", "split", "--table", str(table), "--results", str(results),
                       "--runs", str(tmp_path / "runs"), "--tasks", "metaworld/push"])
    text = table.read_text()
    assert "| push-v3 | 90 (1) | 75 (1) |" in text and "hammer-v3" not in text
    assert 'MeanFlow trained with `meanflow_target="split"`' in text


def test_rl_grid_skips_runs_already_recorded_in_the_results(monkeypatch, tmp_path, capsys):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    assert rl_finetune.planned_recipe([]) == "defaults"
    assert rl_finetune.planned_recipe(["--lr-schedule", "adaptive"]) == "lr_schedule=adaptive"
    results = tmp_path / "rl.json"
    row = {"task": "reach-v3", "decoder": "flow_matching", "algo": "ppo", "recipe": "defaults", "seed": 0,
           "bc": 0.2, "bc_steps": 10, "bc_at_ft_k": 0.2, "ft_k": 10, "ft_sde": 0.5, "ft_ode": 0.4, "cpu_min": 45.0,
           "env_steps": 1000, "measured": "2026-11-23", "curve": []}
    results.write_text(json.dumps([row]))
    ran, bc = [], []
    monkeypatch.setattr(rl_finetune, "run_one", lambda task, dec, seed, args: ran.append((task, dec, seed)))
    monkeypatch.setattr(rl_finetune, "train_bc", lambda task, dec, args: bc.append((task, dec)))
    common = ["--tasks", "metaworld/reach", "--results", str(results), "--runs", str(tmp_path / "runs"),
              "--table", str(tmp_path / "t.md"), "--plot", str(tmp_path / "t.png")]
    rl_finetune.main(common)
    assert ran == [("metaworld/reach-v3", "mean_flow", 0)]           # flow matching's row is recorded
    assert "metaworld/reach-v3 flow_matching seed 0: recorded in" in capsys.readouterr().out
    ran.clear()
    rl_finetune.main([*common, "--", "--lr-schedule", "adaptive"])   # another recipe: both run
    assert ran == [("metaworld/reach-v3", "flow_matching", 0), ("metaworld/reach-v3", "mean_flow", 0)]
    # two seeds, two jobs: each BC policy is trained once, before any fine-tuning starts
    events = []
    monkeypatch.setattr(rl_finetune, "run_one", lambda task, dec, seed, args: events.append(("ft", dec, seed)))
    monkeypatch.setattr(rl_finetune, "train_bc", lambda task, dec, args: events.append(("bc", dec)))
    rl_finetune.main([*common, "--seeds", "0", "1", "--jobs", "2", "--", "--lr-schedule", "adaptive"])
    assert sorted(events[:2]) == [("bc", "flow_matching"), ("bc", "mean_flow")] and len(events) == 6
    assert all(e[0] == "ft" for e in events[2:])


def test_rl_fine_tuning_directory_and_k_follow_the_options(monkeypatch):
    """A recipe gets its own fine-tuning directory, so it never resumes another's run; K is read as
    `finetune` reads it, in either spelling."""
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import rl_finetune

    assert rl_finetune.ft_dir_name([], 0) == "ft" and rl_finetune.ft_dir_name([], 1) == "ft_s1"
    assert rl_finetune.ft_dir_name(["--max-cpu-minutes", "10", "--eval-every", "5"], 0) == "ft"   # budget, logging
    assert rl_finetune.ft_dir_name(["--lr-warmup-updates", "20"], 2) == "ft_lr_warmup_updates-20_s2"
    assert rl_finetune.ft_dir_name(["--sigma", "0.5"], 0) == "ft_sigma-0.5"
    # an option whose default depends on the algorithm is read with the run's algorithm
    assert rl_finetune.ft_dir_name(["--critic-warmup-iters", "10"], 0, "dsrl") == "ft_critic_warmup_iters-10"
    assert rl_finetune.ft_dir_name(["--critic-warmup-iters", "0"], 1, "dsrl") == "ft_s1"
    assert rl_finetune.planned_recipe(["--critic-warmup-iters", "10"], "dsrl") == "critic_warmup_iters=10"
    assert rl_finetune.planned_config(["--sde-steps=5"]).sde_steps == 5
    assert rl_finetune.planned_config(["--sde-steps", "5"]).sde_steps == 5


def test_training_rows_name_the_du_dt_method_they_time(bench_main):
    import benchmarks.suite as suite
    from action_decoder import DecoderConfig

    bc = suite.BenchConfig.preset("tiny")
    variants = suite._train_variants(bc, bc.sizes[0])
    default = DecoderConfig(decoder_type="mean_flow")
    row = variants[suite.MF_DEFAULT_ROW]
    assert (row.meanflow_dudt, row.meanflow_ratio_r_neq_t) == (default.meanflow_dudt, default.meanflow_ratio_r_neq_t)
    jvp = [c for name, c in variants.items() if "JVP" in name]
    assert jvp and all(c.meanflow_dudt == "jvp" for c in jvp)
    assert [c.meanflow_ratio_r_neq_t for c in jvp] == list(bc.mf_ratios)


def test_memory_text_names_the_cpu_analogue_only_on_a_cpu(bench_main):
    from benchmarks.report import render

    cpu = json.loads((ROOT / "docs" / "benchmarks" / "results.json").read_text())
    gpu = json.loads((ROOT / "docs" / "benchmarks" / "gpu" / "results.json").read_text())
    assert (cpu["machine"]["device"], gpu["machine"]["device"]) == ("cpu", "cuda")
    assert "CPU analogue" in render(cpu, None)
    assert "CPU analogue" not in render(gpu, None) and "torch.cuda.max_memory_allocated" in render(gpu, None)


def test_rl_rows_of_another_sigma_budget_or_bc_are_other_runs(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from types import SimpleNamespace

    from benchmarks import rl_finetune

    row = {"task": "door-lock-v3", "decoder": "flow_matching", "algo": "ppo", "seed": 0, "sigma": 0.25, "half": "dev"}
    variants = [row, {**row, "sigma": 0.5}, {**row, "cpu_budget": 90.0}, {**row, "bc_demos": 10},
                {**row, "bc_train_steps": 5000}]
    assert len(rl_finetune.merge(tmp_path / "r.json", variants)) == 5
    assert rl_finetune._key({**row, "cpu_budget": 45.0, "bc_demos": 3, "bc_train_steps": 2000}) == rl_finetune._key(row)
    args = SimpleNamespace(runs="runs", algo="ppo", demos=3, bc_steps=2000)
    assert rl_finetune.run_dir("metaworld/reach", "mean_flow", args).name == "reach_mean_flow"
    args.demos, args.bc_steps = 10, 500
    assert rl_finetune.run_dir("metaworld/reach", "mean_flow", args).name == "reach_mean_flow_demos-10_bc-steps-500"


def test_mlp_reference_column_holds_its_own_replanning_only(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks.metaworld_bc import MLP_N_ACTION_STEPS, matching

    base = {"task": "push-v3", "seed": 0, "decoder": "mlp_baseline", "sampler": "ode", "steps": 10, "success": 0.9}
    rows = [base, {**base, "n_action_steps": MLP_N_ACTION_STEPS, "success": 0.8}, {**base, "n_action_steps": 4},
            {**base, "decoder": "flow_matching", "n_action_steps": 4}, {**base, "decoder": "flow_matching",
                                                                         "n_action_steps": 8}]
    got = matching(rows, {"n_action_steps": 4})
    assert [(r["decoder"], r.get("n_action_steps")) for r in got] == [
        ("mlp_baseline", None), ("mlp_baseline", MLP_N_ACTION_STEPS), ("flow_matching", 4)]


def test_bc_run_or_evaluation_of_other_settings_is_not_reused(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import metaworld_bc

    run = tmp_path / "runs" / "push_s0_flow_matching"
    (run / "final").mkdir(parents=True)
    (run / "final" / "model.safetensors").touch()
    (run / "final" / "config.json").write_text(json.dumps({"state_layout": "metaworld", "decoder_type": "flow_matching",
        "extra": {"train": {"demos": 10, "demo_noise": 0.0, "steps": 5000, "batch_size": 128, "augment_shift": 0.05}}}))
    monkeypatch.setattr(metaworld_bc, "_run", lambda cmd, log: pytest.fail(f"ran {cmd}"))
    args = type("Args", (), {"runs": str(tmp_path / "runs"), "demo_noise": 0.0, "done": {}, "n_action_steps": 4,
                             "episodes": 50, "steps": 1500, "batch_size": 128, "demos": 30,
                             "meanflow_target": "identity", "results": tmp_path / "r.json"})
    with pytest.raises(SystemExit, match=r"made with demos=10, train_steps=5000, not demos=30, train_steps=1500"):
        metaworld_bc.run_one("metaworld/push", 0, "flow_matching", args)
    args.steps, args.demos, args.episodes = 5000, 10, 20
    (run / "eval_ode_k10_n4.json").write_text(json.dumps({"episodes_per_task": 50}))
    with pytest.raises(SystemExit, match=r"eval_ode_k10_n4.json: made with episodes=50, not episodes=20"):
        metaworld_bc.run_one("metaworld/push", 0, "flow_matching", args)


def test_quality_rows_keep_replanning_apart_and_weight_tasks(monkeypatch, tmp_path):
    monkeypatch.syspath_prepend(str(ROOT))
    from benchmarks import suite

    def summary(name, n, per_task):
        (tmp_path / name).write_text(json.dumps({
            "decoder_type": "flow_matching", "sampler": "ode", "steps": 10, "n_action_steps": n, "latency_ms": 5.0,
            "success_rate": sum(per_task.values()) / len(per_task), "per_task": per_task}))

    summary("a.json", 4, {"push-v3": 0.9})
    summary("b.json", 8, {"push-v3": 0.5})
    summary("c.json", 4, {f"t{i}-v3": 0.8 for i in range(10)})
    bc = type("BC", (), {"quality_dir": str(tmp_path), "latency_reps": 1})
    rows = {r["n_action_steps"]: r for r in suite.bench_quality(bc, None)["rows"]
            if (r["decoder"], r["sampler"], r["steps"]) == ("flow_matching", "ode", 10)}
    assert set(rows) == {4, 8} and rows[8]["success_rate"] == 0.5 and rows[4]["n"] == 11
    assert rows[4]["success_rate"] == pytest.approx((0.9 + 8.0) / 11)


def test_export_benchmark_writes_its_page_and_json(tmp_path):
    pytest.importorskip("onnxruntime")
    from benchmarks.export import main

    out = tmp_path / "bench"
    assert main(["--tiny", "--no-compile", "--rounds", "1", "--warmup", "0", "--cases", "mean_flow:1",
                 "--batches", "1", "--out", str(out)]) == 0
    rows = json.loads((out / "export.json").read_text())["rows"]
    assert [(r["decoder"], r["steps"], r["batch"]) for r in rows] == [("mean_flow", 1, 1)]
    assert rows[0]["max_abs_diff"]["ort"] <= 1e-4 and rows[0]["limit_ms"] > 0
    assert "| MeanFlow | 1 | 1 |" in (out / "export.md").read_text()


def test_export_benchmark_gpu_section_sits_beside_the_cpu_one(tmp_path):
    """The CUDA run's rows (eager, CUDA graphs, inductor) render into their own section of export.md."""
    pytest.importorskip("onnxruntime")
    import torch

    from benchmarks import export

    out = tmp_path / "bench"
    assert export.main(["--tiny", "--no-compile", "--rounds", "1", "--warmup", "0", "--cases", "mean_flow:1",
                        "--batches", "1", "--out", str(out)]) == 0
    case = export.build_case("flow_matching", 2, 3, True, False, tmp_path, lambda *a, **k: None, "cpu")
    del case["calls"]["ort1"], case["calls"]["ort2"]         # the paths a CUDA case has, less the compiled ones
    case["calls"]["compiled"] = case["calls"]["inductor"] = case["calls"]["eager"]
    case["compile_s"], case["inductor_compile_s"] = 1.0, 2.0
    rows = export.measure({("flow_matching", 2, 3): case}, 1, 0, lambda *a, **k: None, "cpu")
    assert set(rows[0]["ms"]) == {"eager", "compiled", "inductor"} and rows[0]["limit_ms"] > 0
    assert rows[0]["limit_ms"] == pytest.approx(2 * rows[0]["gflops_call"] / rows[0]["peak_gflops"] * 1e3)
    machine = {"date": "2026-11-27 14:00 UTC", "machine": "test GPU", "torch": torch.__version__, "cuda": "13.0",
               "python": "3.12", "rounds": 1, "warmup": 0, "device": "cuda", "command": "python -m benchmarks export"}
    export.write_page({"machine": machine, "rows": rows, "skipped": ["DDPM:10 B=32"]}, out / "export.md")
    rows[0]["failed"] = {"inductor": "RuntimeError: no kernel"}
    export.write_page({"machine": machine, "rows": rows}, out / "export.md")        # replaces its own section
    text = (out / "export.md").read_text()
    assert "Failed to compile (—): Flow matching K=2 B=3 inductor: RuntimeError: no kernel." in text
    assert text.count(export.GPU_BEGIN) == 1 and text.count(export.BEGIN) == 1
    assert text.index(export.END) < text.index(export.GPU_BEGIN)
    gpu = text.split(export.GPU_BEGIN)[1]
    assert "| Flow matching | 2 | 3 |" in gpu and "test GPU" in gpu and "Not built" not in gpu
    assert "| MeanFlow | 1 | 1 |" in text.split(export.GPU_BEGIN)[0]

    # --append: a second run's rows join the section, each row naming its run; a case that one run skipped and
    # the other built is no longer listed as not built
    second = [dict(rows[0], batch=32, failed={})]
    two = {"runs": [{"machine": machine, "rows": rows, "skipped": ["flow_matching:2 B=32 (past --build-budget-s 1)",
                                                                  "DDPM:10 B=1 (past --build-budget-s 1)"]},
                    {"machine": dict(machine, command="python -m benchmarks export --append"), "rows": second,
                     "skipped": ["DDPM:10 B=1 (past --build-budget-s 9)"]}]}
    export.write_page(two, out / "export.md")
    gpu = (out / "export.md").read_text().split(export.GPU_BEGIN)[1]
    assert "| 1 | Flow matching | 2 | 3 |" in gpu and "| 2 | Flow matching | 2 | 32 |" in gpu
    assert "- Run 2: measured" in gpu and "--append`" in gpu
    assert "Not built: DDPM:10 B=1 (past --build-budget-s 9)." in gpu


def test_export_benchmark_append_is_refused_on_the_cpu(capsys):
    from benchmarks import export

    with pytest.raises(SystemExit):
        export.main(["--append", "--tiny"])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--append: only with --device cuda" in err and "got --device cpu" in err


def test_gpu_benchmarks_refuse_cuda_without_a_gpu_in_one_line(capsys):
    import torch

    if torch.cuda.is_available():
        pytest.skip("a GPU is present")
    from benchmarks import export, rtc_latency

    for main in (export.main, rtc_latency.main):
        with pytest.raises(SystemExit):
            main(["--device", "cuda", "--tiny"])
        assert "--device: cuda needs a CUDA build of torch and a GPU" in capsys.readouterr().err


def test_rtc_latency_times_plain_trained_and_guided_chunks(tmp_path):
    from benchmarks.rtc_latency import main

    out = tmp_path / "rtc.json"
    assert main(["--tiny", "--settings", "flow_matching:2", "--rounds", "1", "--warmup", "0", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["decoder"], r["steps"], r["delay"]) for r in rows] == [("flow_matching", 2, 4)]
    assert set(rows[0]["ms"]) == {"plain", "trained", "guided"} and set(rows[0]["ratio_to_plain"]) == {"trained", "guided"}
