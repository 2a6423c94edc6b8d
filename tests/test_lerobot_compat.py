"""The plugin against LeRobot 0.6's API, without LeRobot: fake `lerobot.*` modules in `sys.modules`.

The fakes hold LeRobot 0.6.1's module layout (no `lerobot.processor.core`, moved in 0.6) and the
0.6 shapes of what the plugin meets there: `PreTrainedPolicy.supports_rtc` (False unless a policy
says otherwise) and the RTC inference engine's call `predict_action_chunk(batch,
inference_delay=d, prev_chunk_left_over=[T, D])` after `policy.config.rtc_config = RTCConfig(...)`
(`lerobot-rollout --inference.type=rtc`), `forward(batch, reduction="none")` (`lerobot-train
--sample_weighting`), dataset metadata whose `tasks` is None when a dataset has none, processor
factories called with `dataset_meta` only when they declare it, and lerobot-train's
`env_eval_freq` (0.4.4: `eval_freq`). The real LeRobot runs in `scripts/lerobot_integration.sh`
(0.4.4 and 0.6.1 virtual environments) and in `tests/test_lerobot_plugin.py` there.
"""

import dataclasses
import enum
import importlib
import importlib.machinery
import inspect
import subprocess
import sys
import types
import warnings
from pathlib import Path
from typing import Any, Generic, Optional, TypeVar

import numpy as np
import pytest
import torch
from torch import nn

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "lerobot_policy_action_decoder" / "src"))
PLUGIN = "lerobot_policy_action_decoder"


# ---------------------------------------------------------------------- fake LeRobot 0.6.1
def _module(name: str, **attrs) -> types.ModuleType:
    mod = types.ModuleType(name)
    mod.__spec__ = importlib.machinery.ModuleSpec(name, None, is_package=True)
    mod.__path__ = []
    mod.__dict__.update(attrs)
    return mod


class FeatureType(str, enum.Enum):
    STATE = "STATE"
    VISUAL = "VISUAL"
    ENV = "ENV"
    ACTION = "ACTION"


class NormalizationMode(str, enum.Enum):
    MIN_MAX = "MIN_MAX"
    MEAN_STD = "MEAN_STD"
    IDENTITY = "IDENTITY"


class RTCAttentionSchedule(str, enum.Enum):           # 0.6: lerobot.configs (0.4.4: lerobot.configs.types)
    ZEROS = "ZEROS"
    ONES = "ONES"
    LINEAR = "LINEAR"
    EXP = "EXP"


@dataclasses.dataclass
class PolicyFeature:
    type: FeatureType
    shape: tuple


@dataclasses.dataclass
class RTCConfig:                                       # lerobot.policies.rtc.configuration_rtc
    enabled: bool = True
    prefix_attention_schedule: RTCAttentionSchedule = RTCAttentionSchedule.LINEAR
    max_guidance_weight: float = 10.0
    execution_horizon: int = 10


class _ChoiceRegistry:
    """draccus' ChoiceRegistry, as far as the plugin uses it."""

    _registry: dict = {}

    def __post_init__(self):
        self.device = self.device or "cpu"

    @classmethod
    def register_subclass(cls, name):
        def deco(sub):
            cls._registry[name] = sub
            sub.type = name
            return sub
        return deco

    @classmethod
    def get_choice_class(cls, name):
        return cls._registry[name]


@dataclasses.dataclass
class PreTrainedConfig04(_ChoiceRegistry):
    """The base fields of 0.4.4's PreTrainedConfig."""

    n_obs_steps: int = 1
    input_features: dict = dataclasses.field(default_factory=dict)
    output_features: dict = dataclasses.field(default_factory=dict)
    device: Optional[str] = None
    use_amp: bool = False
    use_peft: bool = False
    push_to_hub: bool = True
    repo_id: Optional[str] = None
    pretrained_path: Optional[str] = None


@dataclasses.dataclass
class PreTrainedConfig(PreTrainedConfig04):
    """0.6.1's: a Hub revision pin, saved in every config.json (new in 0.6)."""

    pretrained_revision: Optional[str] = None


class PreTrainedPolicy(nn.Module):
    """0.6.1's base: `supports_rtc()` is False unless a policy overrides it."""

    def __init__(self, config, *inputs, **kwargs):
        super().__init__()
        self.config = config

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if not getattr(cls, "config_class", None) or not getattr(cls, "name", None):
            raise TypeError(f"Class {cls.__name__} must define 'config_class' and 'name'")

    def supports_rtc(self) -> bool:
        return False

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path, *, config=None, revision=None, **kwargs):
        return cls(config)


@dataclasses.dataclass
class AdamWConfig:
    lr: float = 1e-3
    betas: tuple = (0.9, 0.999)
    eps: float = 1e-8
    weight_decay: float = 1e-2
    grad_clip_norm: float = 10.0


@dataclasses.dataclass
class DiffuserSchedulerConfig:
    name: str = "cosine"
    num_warmup_steps: Optional[int] = None


class ProcessorStepRegistry:
    _registry = {}

    @classmethod
    def register(cls, name):
        def deco(step):
            cls._registry[name] = step
            step._registry_name = name
            return step
        return deco


class ProcessorStep:
    def get_config(self) -> dict:                      # 0.6 serialises every step's get_config()
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state) -> None:
        return None


class PolicyActionProcessorStep(ProcessorStep):
    def __call__(self, transition):
        return self.action(transition)


def _step(name: str):
    def init(self, **kwargs):
        self.kwargs = kwargs
    return type(name, (ProcessorStep,), {"__init__": init})


TI, TO = TypeVar("TI"), TypeVar("TO")


class PolicyProcessorPipeline(Generic[TI, TO]):
    def __init__(self, steps, name, to_transition=None, to_output=None):
        self.steps, self.name = list(steps), name


@dataclasses.dataclass
class RobotConfig:
    """0.6.1's robot config base (a draccus choice registry), as the simulated robot uses it."""

    id: Optional[str] = None

    @classmethod
    def register_subclass(cls, name):
        return lambda sub: sub

    def __post_init__(self):
        pass


class Robot:
    def __init__(self, config):
        self.config = config


def fake_lerobot(version: str = "0.6.1") -> dict[str, types.ModuleType]:
    """LeRobot's modules as the plugin imports them, in 0.6.1's layout (0.4.x: its config base)."""
    base = PreTrainedConfig if not version.startswith("0.4") else PreTrainedConfig04
    configs_types = _module("lerobot.configs.types", FeatureType=FeatureType, NormalizationMode=NormalizationMode,
                            PolicyFeature=PolicyFeature, RTCAttentionSchedule=RTCAttentionSchedule)
    processor_names = {n: _step(n) for n in ("AddBatchDimensionProcessorStep", "DeviceProcessorStep",
                                             "NormalizerProcessorStep", "RenameObservationsProcessorStep",
                                             "UnnormalizerProcessorStep")}
    pipeline = _module("lerobot.processor.pipeline", PolicyActionProcessorStep=PolicyActionProcessorStep,
                       ProcessorStep=ProcessorStep, ProcessorStepRegistry=ProcessorStepRegistry,
                       PolicyProcessorPipeline=PolicyProcessorPipeline)
    converters = _module("lerobot.processor.converters", policy_action_to_transition=lambda a: a,
                         transition_to_policy_action=lambda t: t)
    return {
        "lerobot": _module("lerobot", __version__=version),
        "lerobot.lerobot_types": _module("lerobot.lerobot_types", PolicyAction=torch.Tensor),
        "lerobot.configs": _module("lerobot.configs", PreTrainedConfig=base, **vars(configs_types)),
        "lerobot.configs.types": configs_types,
        "lerobot.configs.policies": _module("lerobot.configs.policies", PreTrainedConfig=base),
        "lerobot.optim": _module("lerobot.optim", AdamWConfig=AdamWConfig, DiffuserSchedulerConfig=DiffuserSchedulerConfig),
        "lerobot.optim.optimizers": _module("lerobot.optim.optimizers", AdamWConfig=AdamWConfig),
        "lerobot.optim.schedulers": _module("lerobot.optim.schedulers", DiffuserSchedulerConfig=DiffuserSchedulerConfig),
        "lerobot.processor": _module("lerobot.processor", PolicyAction=torch.Tensor, **processor_names,
                                     ProcessorStepRegistry=ProcessorStepRegistry,
                                     PolicyProcessorPipeline=PolicyProcessorPipeline,
                                     PolicyActionProcessorStep=PolicyActionProcessorStep,
                                     policy_action_to_transition=converters.policy_action_to_transition,
                                     transition_to_policy_action=converters.transition_to_policy_action),
        "lerobot.processor.pipeline": pipeline,
        "lerobot.processor.converters": converters,
        "lerobot.utils": _module("lerobot.utils"),
        "lerobot.utils.constants": _module("lerobot.utils.constants",
                                           POLICY_PREPROCESSOR_DEFAULT_NAME="policy_preprocessor",
                                           POLICY_POSTPROCESSOR_DEFAULT_NAME="policy_postprocessor"),
        "lerobot.policies": _module("lerobot.policies"),
        "lerobot.robots": _module("lerobot.robots", RobotConfig=RobotConfig, Robot=Robot),
        "lerobot.robots.config": _module("lerobot.robots.config", RobotConfig=RobotConfig),
        "lerobot.robots.robot": _module("lerobot.robots.robot", Robot=Robot),
        "lerobot.policies.pretrained": _module("lerobot.policies.pretrained", PreTrainedPolicy=PreTrainedPolicy),
    }


def _swap_in(monkeypatch, version: str):
    for name in [m for m in sys.modules if m == "lerobot" or m.startswith(("lerobot.", PLUGIN))]:
        monkeypatch.delitem(sys.modules, name)
    for name, mod in fake_lerobot(version).items():
        monkeypatch.setitem(sys.modules, name, mod)


@pytest.fixture
def lr06(monkeypatch):
    """The plugin imported against fake LeRobot 0.6.1 (real modules back after the test)."""
    _swap_in(monkeypatch, "0.6.1")
    yield importlib.import_module(PLUGIN)
    for name in [m for m in sys.modules if m.startswith(PLUGIN)]:
        del sys.modules[name]


@pytest.fixture
def lr04(monkeypatch):
    """The plugin imported against a fake LeRobot 0.4.4 config base."""
    _swap_in(monkeypatch, "0.4.4")
    yield importlib.import_module(PLUGIN)
    for name in [m for m in sys.modules if m.startswith(PLUGIN)]:
        del sys.modules[name]


def supports_rtc_inference(policy) -> bool:
    """LeRobot 0.6.1's test before `lerobot-rollout --inference.type=rtc` accepts a policy."""
    if not callable(getattr(policy, "supports_rtc", None)) or not policy.supports_rtc():
        return False
    try:
        inspect.signature(policy.predict_action_chunk).bind(object(), inference_delay=0, prev_chunk_left_over=None)
    except (TypeError, ValueError):
        return False
    return True


FEATURES = dict(input_features={"observation.state": PolicyFeature(FeatureType.STATE, (6,))},
                output_features={"action": PolicyFeature(FeatureType.ACTION, (3,))})


def _policy(plugin, **over):
    cfg = plugin.ActionDecoderConfig(hidden_size=32, num_hidden_layers=2, chunk_size=8, n_action_steps=2,
                                     **FEATURES, **over)
    return plugin.ActionDecoderPolicy(cfg, dataset_stats=None, dataset_meta=types.SimpleNamespace(tasks=None)).eval()


# ---------------------------------------------------------------------- tests
def test_the_plugin_imports_from_lerobot_06s_layout_and_registers_its_type(lr06):
    assert "lerobot.processor.core" not in sys.modules        # 0.4.4's module, gone in 0.6
    assert PreTrainedConfig.get_choice_class("action_decoder") is lr06.ActionDecoderConfig
    # LeRobot's factory finds the policy and processor classes by name, beside the config's module.
    config_module = lr06.ActionDecoderConfig.__module__
    modeling = importlib.import_module(config_module.replace("configuration_", "modeling_"))
    processor = importlib.import_module(config_module.replace("configuration_", "processor_"))
    assert getattr(modeling, "ActionDecoderConfig".removesuffix("Config") + "Policy") is lr06.ActionDecoderPolicy
    factory = getattr(processor, "make_action_decoder_pre_post_processors")
    assert "dataset_meta" not in inspect.signature(factory).parameters    # 0.6 passes dataset_stats only, then
    pre, post = factory(lr06.ActionDecoderConfig(**FEATURES), dataset_stats=None)
    assert [type(s).__name__ for s in pre.steps][-1] == "NormalizerProcessorStep"
    assert [type(s).__name__ for s in post.steps] == ["UnnormalizerProcessorStep", "ClipActionsProcessorStep",
                                                      "DeviceProcessorStep"]
    assert post.steps[1].get_config() == {} and post.steps[1].state_dict() == {}   # no bounds: no state file


def test_a_config_saved_by_lerobot_06_loads_where_the_base_has_no_revision_pin(lr04, lr06_config_fields):
    fields = {f.name for f in dataclasses.fields(lr04.ActionDecoderConfig)}
    assert lr06_config_fields <= fields                      # every key a 0.6 config.json holds has a field
    assert lr04.ActionDecoderConfig(pretrained_revision=None).pretrained_revision is None
    with pytest.raises(ValueError, match=r"^policy.pretrained_revision: LeRobot 0.4.4 loads no pinned Hub revision "
                                         r"\(LeRobot >= 0.6 does\); got 'main', expected null$"):
        lr04.ActionDecoderConfig(pretrained_revision="main")


def test_lerobot_06_pins_revisions_itself(lr06):
    assert lr06.ActionDecoderConfig(pretrained_revision="main").pretrained_revision == "main"
    assert "pretrained_revision" in PreTrainedConfig.__dataclass_fields__


@pytest.fixture
def lr06_config_fields(monkeypatch):
    """The field names of the plugin's config under fake LeRobot 0.6.1 (what its config.json holds)."""
    _swap_in(monkeypatch, "0.6.1")
    names = {f.name for f in dataclasses.fields(importlib.import_module(PLUGIN).ActionDecoderConfig)}
    for name in [m for m in sys.modules if m.startswith(PLUGIN)]:
        del sys.modules[name]
    return names


def test_a_policy_of_a_dataset_without_tasks_builds(lr06):
    policy = _policy(lr06)                                     # 0.6 metadata: tasks None when there are none
    assert policy.config.tasks == [] and policy.decoder.config.context_dim is None


@pytest.mark.parametrize("decoder, rtc", [("flow_matching", True), ("mean_flow", True), ("DDPM", False)])
def test_lerobot_06_rtc_engine_accepts_flow_decoders(lr06, decoder, rtc):
    assert supports_rtc_inference(_policy(lr06, decoder_type=decoder)) is rtc


@pytest.mark.parametrize("decoder", ["flow_matching", "mean_flow"])
def test_lerobot_06_rtc_call_commits_the_left_over_and_returns_a_chunk(lr06, decoder):
    torch.manual_seed(0)
    policy = _policy(lr06, decoder_type=decoder)
    obs = {"observation.state": torch.randn(1, 6)}
    left = torch.randn(6, 3)                                  # [T, D]: LeRobot's queue left-over, normalised
    noise = torch.randn(1, 8, 3)
    chunk = policy.predict_action_chunk(obs, noise=noise, inference_delay=2, prev_chunk_left_over=left)
    assert chunk.shape == (1, 8, 3) and torch.isfinite(chunk).all()
    assert torch.equal(chunk[0, :2], left[:2])                # the actions executed while sampling are the left-over's
    again = policy.predict_action_chunk(obs, noise=noise, inference_delay=np.int64(2), prev_chunk_left_over=left)
    assert torch.equal(again, chunk)                          # a NumPy integer delay is a delay too
    plain = policy.predict_action_chunk(obs, noise=noise)
    assert not torch.allclose(chunk[0, 2:6], plain[0, 2:6])   # the overlap is guided towards the left-over
    first = policy.predict_action_chunk(obs, noise=noise, inference_delay=3, prev_chunk_left_over=None)
    assert torch.equal(first, plain)                          # the first chunk: nothing committed
    late = policy.predict_action_chunk(obs, noise=noise, inference_delay=9, prev_chunk_left_over=left[:4])
    assert torch.equal(late[0, :4], left[:4])                 # a delay past the left-over commits all of it


def test_lerobot_06_rtc_config_sets_weight_schedule_and_horizon_for_the_call(lr06, monkeypatch):
    policy = _policy(lr06)
    seen = []
    real = policy.decoder.predict_action_chunk

    def recording(batch, *args, prev_chunk=None, delay=0, **kwargs):
        seen.append((policy.decoder.config.rtc_guidance_weight, policy.decoder.config.rtc_schedule,
                     None if prev_chunk is None else prev_chunk.shape[1], delay))
        return real(batch, *args, prev_chunk=prev_chunk, delay=delay, **kwargs)

    monkeypatch.setattr(policy.decoder, "predict_action_chunk", recording)
    obs, left = {"observation.state": torch.randn(1, 6)}, torch.randn(7, 3)
    policy.predict_action_chunk(obs, inference_delay=1, prev_chunk_left_over=left)
    policy.config.rtc_config = RTCConfig(prefix_attention_schedule=RTCAttentionSchedule.ONES, max_guidance_weight=2.5,
                                         execution_horizon=4)                 # what lerobot-rollout sets
    policy.predict_action_chunk(obs, inference_delay=1, prev_chunk_left_over=left)
    policy.predict_action_chunk(obs)
    assert seen == [(5.0, "exp", 7, 1), (2.5, "ones", 4, 1), (5.0, "exp", None, 0)]
    assert (policy.decoder.config.rtc_guidance_weight, policy.decoder.config.rtc_schedule) == (5.0, "exp")


@pytest.mark.parametrize("call, match", [
    (dict(inference_delay=-1, prev_chunk_left_over=torch.zeros(4, 3)), r"^inference_delay: expected a non-negative"),
    (dict(inference_delay=1, prev_chunk_left_over=torch.zeros(4, 5)),
     r"^prev_chunk_left_over: expected a float tensor \[T, 3\] or \[1, T, 3\].*got \[4, 5\]$"),
])
def test_bad_rtc_arguments_are_one_line(lr06, call, match):
    with pytest.raises(ValueError, match=match):
        _policy(lr06).predict_action_chunk({"observation.state": torch.randn(1, 6)}, **call)


def test_ddpm_refuses_a_left_over_and_a_bad_rtc_config_is_named(lr06):
    obs, left = {"observation.state": torch.randn(1, 6)}, torch.zeros(4, 3)
    with pytest.raises(ValueError, match=r"^prev_chunk_left_over: real-time chunking needs a flow_matching or "
                                         r"mean_flow decoder, got DDPM$"):
        _policy(lr06, decoder_type="DDPM").predict_action_chunk(obs, inference_delay=1, prev_chunk_left_over=left)
    policy = _policy(lr06)
    policy.config.rtc_config = RTCConfig(prefix_attention_schedule="COSINE")
    with pytest.raises(ValueError, match=r"^rtc_config.prefix_attention_schedule: expected one of \['EXP'"):
        policy.predict_action_chunk(obs, inference_delay=1, prev_chunk_left_over=left)


def test_per_sample_losses_for_sample_weighting_are_refused_in_one_line(lr06):
    batch = {"observation.state": torch.randn(2, 6), "action": torch.randn(2, 8, 3)}
    with pytest.raises(ValueError, match=r"^reduction: expected 'mean' .*--sample_weighting.*got 'none'$"):
        _policy(lr06).forward(batch, reduction="none")
    loss, info = _policy(lr06).train().forward(batch)
    assert loss.dim() == 0 and info["loss"] == pytest.approx(loss.item())


def test_lerobot_versions_outside_the_supported_range(monkeypatch):
    _swap_in(monkeypatch, "0.4.2")
    with pytest.raises(ImportError, match=r"^lerobot_policy_action_decoder: LeRobot 0.4.2 is not supported; "
                                          r"expected lerobot>=0.4.3,<0.7"):
        importlib.import_module(PLUGIN)
    for version, warns in (("0.7.0", True), ("0.6.1", False), ("0.4.4", False)):
        _swap_in(monkeypatch, version)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            importlib.import_module(PLUGIN)
        assert any(f"LeRobot {version} is newer" in str(w.message) for w in caught) is warns, version
    for name in [m for m in sys.modules if m.startswith(PLUGIN)]:
        del sys.modules[name]


@pytest.mark.parametrize("field, flag", [("env_eval_freq", "--env_eval_freq=0"), ("eval_freq", "--eval_freq=0")])
def test_integration_script_turns_env_evaluation_off_with_each_versions_flag(tmp_path, field, flag):
    """lerobot-train 0.6+ has `env_eval_freq` where 0.4.4 had `eval_freq` (and refuses the other name)."""
    pkg = tmp_path / "lerobot" / "configs"
    pkg.mkdir(parents=True)
    for d in (tmp_path / "lerobot", pkg):
        (d / "__init__.py").write_text("")
    (pkg / "train.py").write_text(f"import dataclasses\n@dataclasses.dataclass\nclass TrainPipelineConfig:\n"
                                  f"    {field}: int = 20000\n    log_freq: int = 200\n")
    script = (ROOT / "scripts" / "lerobot_integration.sh").read_text()
    body = script[script.index("no_env_eval() {"):]
    body = body[: body.index("\n}\n") + 3]
    out = subprocess.run(["bash", "-c", f"{body}\nno_env_eval"], capture_output=True, text=True, timeout=60,
                         env={"PY": sys.executable, "PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == flag
