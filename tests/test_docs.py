"""The documentation a user reads: the site builds strictly, the API reference covers the public
names, the README stays short and its quick start runs, and the repository never narrates how it
was made."""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "docs" / "reference"
README_MAX_LINES = 150


def _mkdocs_build(root: Path, site: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1", "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
                          cwd=root, env=env, capture_output=True, text=True, timeout=300)


def _described_entries(html: str) -> dict[str, bool]:
    """Each rendered API entry's id → whether it has text of its own (a paragraph in its contents before
    its first member)."""
    entries = {}
    for heading in re.finditer(r'<h\d id="([^"]+)" class="doc doc-heading">', html):
        rest = html[heading.end():]
        start = rest.find('<div class="doc doc-contents')
        member = re.search(r'<div class="doc doc-(object|children)', rest[start + 1:])
        entries[heading[1]] = "<p>" in rest[start:start + 1 + (member.start() if member else len(rest))]
    return entries


@pytest.fixture(scope="module")
def mkdocs_available():
    if importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None:
        pytest.skip("mkdocs / mkdocstrings not installed (the [docs] extra)")


def test_mkdocs_build_strict_passes_and_renders_every_public_name(mkdocs_available, tmp_path):
    import action_decoder.data
    import action_decoder.flows
    import action_decoder.rl

    site = tmp_path / "site"
    res = _mkdocs_build(ROOT, site)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    for page in ("index.html", "guides/vlm_conditioning/index.html", "benchmarks/metaworld_bc/index.html"):
        assert (site / page).is_file(), page
    html = {p: (site / "reference" / p / "index.html").read_text() for p in ("flows", "data", "rl", "policy")}
    anchors = [("flows", f"action_decoder.flows.{n}") for n in action_decoder.flows.__all__]
    anchors += [("data", f"action_decoder.data.{n}") for n in action_decoder.data.__all__]
    anchors += [("rl", "action_decoder.rl.FinetuneConfig"), ("rl", "action_decoder.rl.finetune.finetune")]
    anchors += [("policy", f"action_decoder.{n}") for n in ("policy.ActionDecoderPolicy", "policy.PolicyOutput",
                                                            "config.DecoderConfig")]
    missing = [name for page, name in anchors if f'id="{name}"' not in html[page]]
    assert not missing, f"rendered without a documented entry: {missing}"
    # Every entry of the policy page says what it is: DecoderConfig's fields above all (attribute
    # docstrings; `#` comments never reach the reference).
    from dataclasses import fields

    from action_decoder import DecoderConfig

    described = _described_entries(html["policy"])
    config_fields = [f"action_decoder.config.DecoderConfig.{f.name}" for f in fields(DecoderConfig)]
    assert all(name in described for name in config_fields), [n for n in config_fields if n not in described]
    bare = [name for name, has_text in described.items() if not has_text]
    assert not bare, f"rendered without a description: {bare}"
    assert set(action_decoder.rl.__all__) == {"FinetuneConfig", "finetune"}


@pytest.mark.parametrize("breakage", ["link", "reference"])
def test_mkdocs_build_strict_fails_on_a_broken_reference(mkdocs_available, tmp_path, breakage):
    """The same build on a copy with one broken cross-page anchor, or one `:::` to a name that
    does not exist, must fail: that is what makes the CI check worth having."""
    copy = tmp_path / "repo"
    shutil.copytree(ROOT / "docs", copy / "docs")
    shutil.copy(ROOT / "mkdocs.yml", copy / "mkdocs.yml")
    os.symlink(ROOT / "src", copy / "src")
    page = copy / "docs" / "reference" / "index.md"
    text = page.read_text()
    if breakage == "link":
        broken = text.replace("flows.md#action_decoder.flows.sample_ode)", "flows.md#action_decoder.flows.no_such_sampler)")
    else:
        broken = text + "\n::: action_decoder.flows.no_such_function\n"
    assert broken != text
    page.write_text(broken)
    res = _mkdocs_build(copy, tmp_path / "site")
    assert res.returncode != 0
    assert "no_such" in res.stdout + res.stderr


def test_api_reference_covers_every_public_name():
    import action_decoder
    import action_decoder.data
    import action_decoder.flows
    import action_decoder.rl

    pages = {p.name: p.read_text() for p in REFERENCE.glob("*.md")}
    index = pages["index.md"]
    missing = [n for n in action_decoder.__all__ if f"`{n}`" not in index]
    assert not missing, f"docs/reference/index.md lacks {missing}"
    # Each subpackage page renders its module, whose __all__ mkdocstrings documents in full.
    for page, module in (("flows.md", "action_decoder.flows"), ("data.md", "action_decoder.data"),
                         ("rl.md", "action_decoder.rl"), ("oracles.md", "action_decoder.oracles")):
        assert re.search(rf"^::: {re.escape(module)}\s*$", pages[page], re.M), (page, module)
    # Names exported at the top level but defined outside flows are rendered on their own.
    everything = "\n".join(pages.values())
    for name in ("action_decoder.policy.ActionDecoderPolicy", "action_decoder.policy.PolicyOutput",
                 "action_decoder.config.DecoderConfig", "action_decoder.train.TrainConfig",
                 "action_decoder.evaluate.EvalConfig", "action_decoder.record.RecordConfig"):
        assert f"::: {name}" in everything, name
    flows_names = set(action_decoder.flows.__all__)
    top_level = set(action_decoder.__all__) - {"ActionDecoderPolicy", "PolicyOutput", "DecoderConfig"}
    assert top_level <= flows_names, top_level - flows_names


def test_readme_is_short():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, expected at most {README_MAX_LINES}"


def _tracked_text_files() -> list[Path]:
    if shutil.which("git") is None:
        pytest.skip("git not installed")
    res = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True)
    if res.returncode != 0:
        pytest.skip("not a git checkout")
    files = []
    for name in res.stdout.decode().split("\0"):
        path = ROOT / name
        if name and path.is_file():
            head = path.read_bytes()[:8192]
            if b"\0" not in head:              # binary (images, parquet) is skipped
                files.append(path)
    return files


def test_no_tracked_file_narrates_how_it_was_made():
    word = "sess" + "ion"                       # spelled apart so this file passes its own check
    offenders = []
    for path in _tracked_text_files():
        for i, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            if word in line.lower():
                offenders.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:100]}")
    assert not offenders, "\n".join(offenders[:20])


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), re.S)


def test_readme_quick_start_runs(tmp_path, monkeypatch):
    """The README's quick start, as written: a LeRobot fixture dataset, its statistics, training,
    sampling, save and reload."""
    block = next(b for b in _python_blocks(ROOT / "README.md") if "load_dataset" in b)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tests").symlink_to(ROOT / "tests")
    scope: dict = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert scope["chunk"].shape == (2, 16, scope["data"].actions.shape[1])
    assert (tmp_path / "ckpt" / "model.safetensors").is_file()
    norm = scope["policy"].normalizers["state"]
    assert norm.mean.numpy() == pytest.approx(scope["data"].states.mean(0), abs=1e-4), "stats reached the policy"


def test_vlm_guide_example_runs():
    pytest.importorskip("transformers")
    blocks = [b for b in _python_blocks(ROOT / "docs" / "guides" / "vlm_conditioning.md") if "vlm_key_values" in b]
    assert len(blocks) == 1
    scope: dict = {}
    exec(compile(blocks[0], "vlm_conditioning.md", "exec"), scope)
    cache, policy = scope["cache"], scope["policy"]
    assert policy.model.conditioning.vlm_k_proj[0].weight.grad.abs().sum() > 0, "the cache conditions training"
    assert len(cache.layers) == policy.config.vlm_num_layers


def _run_in(block: str, name: str, where) -> dict:
    """Execute a guide's Python block with `where` as the working directory; returns its names."""
    scope: dict = {}
    cwd = os.getcwd()
    os.chdir(where)
    try:
        exec(compile(block, name, "exec"), scope)
    finally:
        os.chdir(cwd)
    return scope


def test_cameras_guide_example_runs():
    """The cameras guide trains and samples a camera policy on the LeRobot-written camera fixture."""
    blocks = [b for b in _python_blocks(ROOT / "docs" / "guides" / "cameras.md") if "v30_cams" in b]
    assert len(blocks) == 1
    scope = _run_in(blocks[0], "cameras.md", ROOT)
    assert scope["chunk"].shape[1:] == (8, 2) and scope["policy"].config.cameras == (
        "observation.images.top", "observation.images.wrist")


def test_real_time_chunking_guide_loop_runs_as_written(tmp_path):
    """The guide's control loop, on a small flow-matching checkpoint saved where it loads one from."""
    import torch

    from action_decoder import ActionDecoderPolicy, DecoderConfig

    blocks = [b for b in _python_blocks(ROOT / "docs" / "guides" / "real_time_chunking.md") if "prev_chunk=" in b]
    assert len(blocks) == 1
    torch.manual_seed(0)
    ActionDecoderPolicy(DecoderConfig(decoder_type="flow_matching", hidden_size=32, num_hidden_layers=1,
                                      num_inference_timesteps=2)).save_pretrained(tmp_path / "runs" / "push" / "final")
    scope = _run_in(blocks[0], "real_time_chunking.md", tmp_path)
    s, d, chunk, queue = scope["s"], scope["d"], scope["chunk"], scope["queue"]
    assert len(queue) == s + d and all(torch.equal(a, b) for a, b in zip(queue, chunk[0, : s + d]))


def test_every_dataset_a_guide_records_is_used():
    """A `record --output-dir DIR` in a page's commands is followed by a command that reads DIR."""
    for page in [ROOT / "README.md", *sorted((ROOT / "docs" / "guides").glob("*.md"))]:
        commands = "\n".join(re.findall(r"```bash\n(.*?)```", page.read_text(), re.S))
        for match in re.finditer(r"action-decoder record .*?--output-dir (\S+)", commands):
            later = commands[match.end():]
            assert f"--dataset {match[1]}" in later or f"root={match[1]}" in later, \
                f"{page.name}: records {match[1]} and never uses it"
