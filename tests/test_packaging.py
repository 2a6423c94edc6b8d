"""pyproject.toml declares what the code imports, with bounds that cover the features it uses;
the optional extras ([vlm], [sim], [dist]) stay optional."""

import ast
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src" / "action_decoder"
LAUNCHERS = {"accelerate"}         # declared for `accelerate launch`, never imported
# The [docs] extra: `python -m mkdocs build` (tests/test_docs.py) runs them, nothing imports them.
LAUNCHERS |= {"mkdocs", "mkdocs-material", "mkdocstrings", "mkdocstrings-python"}
# The [test] extra's pytest plugin: the README's test command (`pytest -n auto`) loads it, nothing imports it.
LAUNCHERS |= {"pytest-xdist"}
# (file under src/action_decoder, code it contains, distribution, oldest release that runs it)
FEATURES = [("expert/attention.py", "enable_gqa=True", "torch", (2, 5)),
            ("expert/conditioning.py", '"layers"', "transformers", (4, 54))]    # Cache.layers[i].keys


DISTRIBUTIONS = {"PIL": "pillow"}   # import name -> distribution name, where they differ


def _name(req: str) -> str:
    return re.split(r"[<>=!~\[;\s]", req, maxsplit=1)[0].lower()


def _declared() -> tuple[dict, dict]:
    tomllib = pytest.importorskip("tomllib")                    # Python ≥ 3.11
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = {_name(r): r for r in project["dependencies"]}
    extras = {k: {_name(r): r for r in v if _name(r) != "action-decoder"}
              for k, v in project["optional-dependencies"].items()}
    return core, extras


def _imports(*roots: Path) -> set:
    found = set()
    for root in roots:
        for path in root.rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    found |= {a.name.split(".")[0] for a in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    found.add(node.module.split(".")[0])
                elif (isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "importorskip"
                      and node.args and isinstance(node.args[0], ast.Constant)):
                    found.add(node.args[0].value.split(".")[0])          # pytest.importorskip("x")
    found = {DISTRIBUTIONS.get(name, name) for name in found}
    return found - set(sys.stdlib_module_names) - {"action_decoder", "benchmarks", "conftest"}


def test_every_import_is_declared_and_every_required_dependency_is_imported():
    core, extras = _declared()
    optional = {name for reqs in extras.values() for name in reqs}
    used = _imports(SRC)
    assert used <= set(core) | optional, f"imported but not declared: {sorted(used - set(core) - optional)}"
    assert set(core) <= used, f"required but never imported by the library: {sorted(set(core) - used)}"
    unused = optional - _imports(SRC, ROOT / "tests", ROOT / "benchmarks") - LAUNCHERS
    assert not unused, f"extras nothing imports: {sorted(unused)}"
    tomllib = pytest.importorskip("tomllib")
    test_extra = " ".join(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]["test"])
    pulled = set(re.search(r"action-decoder\[([^\]]*)\]", test_extra).group(1).split(","))
    assert {"sim", "vlm"} <= pulled, f"[test] must pull [sim] and [vlm] (their tests import them), got {pulled}"


def test_declared_minimums_cover_the_features_the_code_uses():
    core, extras = _declared()
    declared = {**{n: r for reqs in extras.values() for n, r in reqs.items()}, **core}
    for file, code, dist, oldest in FEATURES:
        assert code in (SRC / file).read_text(), f"{file} no longer uses {code}: update FEATURES"
        bound = re.search(r">=\s*([\d.]+)", declared[dist])
        assert bound, f"{dist}: no lower bound in {declared[dist]!r}"
        got = tuple(int(x) for x in bound.group(1).split(".")[:2])
        assert got >= oldest, f"{dist}>={bound.group(1)} but {file} uses {code} (needs {oldest})"


def test_policy_trains_and_samples_without_the_optional_extras():
    """With transformers, accelerate and the simulator packages unimportable, the library still
    imports, trains and samples (KV cache as (K, V) pairs); a cache of transformers < 4.54
    gets one line naming the [vlm] extra."""
    code = textwrap.dedent("""
        import sys
        for m in ("transformers", "accelerate", "metaworld", "gymnasium", "mujoco", "pyarrow"):
            sys.modules[m] = None                                 # `import m` raises ImportError
        import torch
        import action_decoder.cli, action_decoder.train, action_decoder.evaluate
        from action_decoder import ActionDecoderPolicy, DecoderConfig
        cfg = DecoderConfig(decoder_type="mean_flow", state_dim=3, action_dim=2, action_chunk_size=4,
                            hidden_size=16, num_hidden_layers=2, num_attention_heads=2, num_key_value_heads=1,
                            vlm_num_layers=2, vlm_head_dim=4, vlm_num_key_value_heads=1)
        policy = ActionDecoderPolicy(cfg)
        kv = [(torch.randn(2, 1, 5, 4), torch.randn(2, 1, 5, 4)) for _ in range(2)]
        b = {"state": torch.randn(2, 3), "vlm_key_values": kv}
        policy.compute_loss({**b, "actions": torch.randn(2, 4, 2)}).loss.backward()
        assert policy.predict_action_chunk(b).shape == (2, 4, 2)
        class OldCache:                                           # transformers < 4.54's DynamicCache
            key_cache, value_cache = [k for k, _ in kv], [v for _, v in kv]
        try:
            policy.predict_action_chunk({**b, "vlm_key_values": OldCache()})
        except ValueError as e:
            print(e)
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])})
    assert res.returncode == 0, res.stderr[-2000:]
    assert "action-decoder[vlm]" in res.stdout and "4.54" in res.stdout, res.stdout
