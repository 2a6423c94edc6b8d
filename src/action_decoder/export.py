"""The deterministic sampler of a policy as one graph: ONNX export.

`ChunkSampler` is a module whose forward is the whole chunk of `predict_action_chunk` for a
given noise: the state's normalisation (and layout features), the conditioning prefix, the K
network calls of the sampler unrolled with their times as constants, the un-normalisation and
the squash. DDPM's DPM-Solver++ keeps a multistep history; its update is linear in the sample,
the network output and the previous x0 prediction, so the coefficients are read off diffusers'
scheduler once (`dpm_solver_coefficients`) and stored as constants.

`export_onnx` writes the graph with `torch.onnx.export` and stores what a runtime needs in the
file's `metadata_props` (key `action_decoder`, JSON): input names and shapes, the chunk shape,
the decoder, sampler and K. `action_decoder.runtime` reads it back without PyTorch.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Optional

import torch
from torch import Tensor, nn

from .expert.conditioning import Prefix
from .flows.ddpm import _clip_x0, inference_scheduler
from .flows.paths import check_steps, time_grid, velocity_from_sample
from .state_layout import network_state

if TYPE_CHECKING:
    from .policy import ActionDecoderPolicy

METADATA_KEY = "action_decoder"
STATE, NOISE, CONTEXT, CONTEXT_MASK, IMAGES, ACTION = (
    "observation.state", "noise", "context", "context_mask", "observation.images", "action")
COMMITTED, DELAY = "committed_actions", "delay"          # the trained-RTC graph's inputs (`ChunkSampler(rtc=True)`)
OPSET = 18
EXPORTERS = ("dynamo", "torchscript")


@dataclass(frozen=True)
class DPMStep:
    """One DPM-Solver++ step as constants: the network's time `t` (library convention), then
    x' = a·x + b·out + c·h and h' = p·x + q·out, with h the previous step's x0 prediction and
    out the network output (clipped first with `alpha_bar` when `clip_sample`)."""

    t: float
    alpha_bar: float
    a: float
    b: float
    c: float
    p: float
    q: float


def dpm_solver_coefficients(config, steps: int) -> list[DPMStep]:
    """Read each step's linear update off diffusers' own `DPMSolverMultistepScheduler.step` (the one
    `flows.sample_ddpm` runs), by stepping it on unit probes: every update of DPM-Solver++ is linear in
    the sample, the converted model output and the stored previous one."""
    check_steps(steps)
    if steps > config.num_train_timesteps:
        raise ValueError(f"steps: expected at most num_train_timesteps={config.num_train_timesteps}, got {steps}")
    sched = inference_scheduler(config)
    sched.set_timesteps(steps)
    alphas = sched.alphas_cumprod
    eye = torch.eye(3)                                           # probes: x, out, h (one per row)
    rows = []
    for k, step in enumerate(sched.timesteps):
        if k > 0:                       # the scheduler's history slot for the previous x0 prediction
            sched.model_outputs[-1] = eye[2]
        x_next = sched.step(eye[1], step, eye[0]).prev_sample     # [3]: a, b, c
        x0 = sched.model_outputs[-1]                              # [3]: p, q, 0
        t = 1.0 - step.reshape(1).float() / config.num_train_timesteps      # float32, as the policy maps it
        rows.append(DPMStep(t=float(t), alpha_bar=float(alphas[step]),
                            a=float(x_next[0]), b=float(x_next[1]), c=float(x_next[2]) if k > 0 else 0.0,
                            p=float(x0[0]), q=float(x0[1])))
    sched.set_timesteps(steps)          # leave the shared scheduler as a fresh sampling call finds it
    return rows


def export_refusal(policy: "ActionDecoderPolicy", sampler: Optional[str]) -> Optional[str]:
    """The one-line reason this policy/sampler cannot be exported, or None."""
    cfg = policy.config
    chosen = sampler or cfg.default_sampler
    if chosen == "sde":
        return ("sampler: the SDE sampler draws fresh noise at every step and is not exported; export the "
                "deterministic sampler (sampler='ode' or None)")
    if cfg.noise_actor_hidden:
        return ("noise_actor_hidden: a noise-space (finetune --algo dsrl) policy draws its noise from its noise "
                "actor, which the graph, whose input is the noise itself, does not hold; export the BC checkpoint "
                "and feed it the actor's noise (policy.noise_actor.sample)")
    if cfg.n_obs_steps > 1:
        return (f"n_obs_steps: the exported and compiled samplers take one observation (state [B, S]); this policy "
                f"conditions on the last {cfg.n_obs_steps} (n_obs_steps={cfg.n_obs_steps}): sample it with "
                f"policy.predict_action_chunk")
    if cfg.uses_vlm_cache:
        return ("vlm_key_values: a policy conditioned on a VLM's KV cache is not exported (the cache is a "
                "per-layer structure of the VLM's own shapes); export a policy with context tokens or cameras")
    if cfg.decoder_type == "mean_flow" and chosen == "euler" and cfg.meanflow_sde_velocity == "identity":
        return ("meanflow_sde_velocity: 'identity' differentiates the network (torch.func.jvp) at every step and "
                "is not exported; export sampler='ode' (MeanFlow's own) or a 'boundary' velocity")
    return None


def rtc_refusal(policy: "ActionDecoderPolicy", sampler: Optional[str]) -> Optional[str]:
    """The one-line reason this policy/sampler has no trained real-time chunking graph, or None."""
    cfg = policy.config
    chosen = policy.resolve_sampler(sampler)
    if not cfg.rtc_max_delay:
        return ("rtc: the graph feeds committed actions to a checkpoint trained with real-time chunking "
                "(train --rtc-max-delay N); this one has rtc_max_delay=0")
    if not policy.feeds_prefix(chosen):
        return (f"rtc: the committed prefix is fed to the ODE sampler ('ode'"
                f"{', or euler' if cfg.decoder_type == 'flow_matching' else ''}), got sampler={chosen!r}")
    return None


class ChunkSampler(nn.Module):
    """forward(state [B, S] env units, noise [B, H, D], context [B, L, C]?, context_mask [B, L]?,
    images [B, N_cam, 3, S, S] uint8?, committed [B, M, D]?, delay [B]?) → actions [B, H, D] env units:
    `predict_action_chunk` for that noise, with the sampler's K network calls unrolled.

    With `rtc=True` (checkpoints trained with `rtc_max_delay` M > 0) the graph is trained real-time
    chunking (`flows/rtc_trained.py`): row b's first delay[b] ∈ 0..M actions are committed[b]'s (env
    units), fed in clean at t = 1 on every step and returned exactly; committed's rows past delay[b]
    are ignored, and delay[b] = 0 is the plain chunk. It is `sample(prev_chunk=committed,
    delay=d, rtc_mode="trained")` with the delay an input, so one graph serves every delay."""

    def __init__(self, policy: "ActionDecoderPolicy", sampler: Optional[str] = None, steps: Optional[int] = None,
                 rtc: bool = False):
        super().__init__()
        refusal = export_refusal(policy, sampler) or (rtc_refusal(policy, sampler) if rtc else None)
        if refusal:
            raise ValueError(refusal)
        self.rtc = bool(rtc)
        self.max_delay = policy.config.rtc_max_delay if rtc else 0
        self.policy = policy
        cfg = policy.config
        self.sampler = policy.resolve_sampler(sampler)
        self.steps = policy.resolve_steps(self.sampler, steps)
        if cfg.decoder_type == "DDPM":
            self.kind = "ddpm"
            self.ddpm = dpm_solver_coefficients(cfg, self.steps)
        else:
            self.kind = "meanflow" if cfg.decoder_type == "mean_flow" and self.sampler == "ode" else "euler"
            grid = time_grid(self.steps)                        # float32, as the samplers integrate on
            self.times = list(zip(grid[:-1].tolist(), grid[1:].tolist(), grid.diff().tolist()))

    def _prefix(self, context: Optional[Tensor], context_mask: Optional[Tensor],
                images: Optional[Tensor]) -> Optional[Prefix]:
        """The conditioning prefix without `Prefix`'s host check of the mask: masked attention
        whenever a mask is an input (an all-True mask gives the unmasked result)."""
        enc = self.policy.model.conditioning
        parts = []
        if context is not None:
            parts.append(enc._from_context(context, context_mask))
        if images is not None:
            tokens = self.policy.model.image_encoder(images)                          # [B, N·T, hidden]
            parts.append(enc._tokens_kv(enc.image_kv, enc.image_norm(tokens),
                                        torch.ones(tokens.shape[:2], dtype=torch.bool, device=tokens.device)))
        if not parts:
            return None
        prefix = Prefix.__new__(Prefix)
        prefix.keys = tuple(torch.cat([p[0][i] for p in parts], dim=2) for i in range(enc.num_layers))
        prefix.values = tuple(torch.cat([p[1][i] for p in parts], dim=2) for i in range(enc.num_layers))
        prefix.mask = torch.cat([p[2] for p in parts], dim=1)
        prefix.all_valid = context is None or context_mask is None
        return prefix

    def forward(self, state: Tensor, noise: Tensor, context: Optional[Tensor] = None,
                context_mask: Optional[Tensor] = None, images: Optional[Tensor] = None,
                committed: Optional[Tensor] = None, delay: Optional[Tensor] = None) -> Tensor:
        policy, cfg = self.policy, self.policy.config
        raw = state.float()                                                           # [B, S]
        s = network_state(cfg.state_layout, policy.normalizers["state"].normalize(raw), raw)
        prefix = self._prefix(context, context_mask, images)
        x = noise.float()                                                             # [B, H, D]
        if self.rtc:
            if committed is None or delay is None:
                raise ValueError(f"committed, delay: this sampler (rtc=True) takes the committed actions [B, "
                                 f"{self.max_delay}, D] and the delays [B] (0: a plain chunk); got "
                                 f"{'no committed' if committed is None else 'no delay'}")
            return self._trained_rtc(s, prefix, x, committed, delay)

        def const(v: float) -> Tensor:                       # a constant of the graph, on the chunk's device
            return torch.tensor(v, device=x.device)

        def net(x: Tensor, t: float, r: float) -> Tensor:
            return policy.model(x, const(t), const(r), s, prefix=prefix).float()

        if self.kind == "ddpm":
            h = torch.zeros_like(x)
            for st in self.ddpm:
                out = net(x, st.t, st.t)
                if cfg.clip_sample:
                    out = _clip_x0(out, x, const(st.alpha_bar), cfg.prediction_type)
                x, h = st.a * x + st.b * out + st.c * h, st.p * x + st.q * out
        else:
            for t, r, dt in self.times:
                if self.kind == "meanflow":
                    x = x + dt * self._velocity(net(x, t, r), x, t)
                else:
                    x = x + dt * self._velocity(net(x, t, t), x, t)
        return policy._env_actions(x)

    def _trained_rtc(self, s: Tensor, prefix: Optional[Prefix], x: Tensor, committed: Tensor,
                     delay: Tensor) -> Tensor:
        """The chunk with row b's first delay[b] rows committed (`sample_ode_prefix`, `sample_meanflow_prefix`
        with the kept rows a per-row mask instead of a slice)."""
        policy, cfg = self.policy, self.policy.config
        b, horizon, dim = x.shape
        keep = torch.arange(horizon, device=x.device)[None, :] < delay.to(x.device)[:, None]     # [B, H] bool
        pad = torch.zeros(b, horizon - committed.shape[1], dim, device=x.device)
        env = torch.cat([committed.float(), pad], 1)                                  # [B, H, D] env units
        if cfg.action_squash:        # back through tanh (atanh spelt out: the TorchScript exporter lacks it)
            inside = env.clamp(-1 + 1e-6, 1 - 1e-6)
            clean = 0.5 * torch.log((1 + inside) / (1 - inside))
        else:
            clean = env
        rows = keep[..., None]                                                        # [B, H, 1]
        clean = policy.normalizers["actions"].normalize(clean)                        # [B, H, D]
        for t, r, dt in self.times:
            r = r if self.kind == "meanflow" else t
            x = torch.where(rows, clean, x)               # the kept rows enter every step clean, whatever moved them
            # Kept rows at t = r = 1 (`clean_rows`): the time embeddings stay constants of the graph.
            out = policy.model(x, torch.tensor(t, device=x.device), torch.tensor(r, device=x.device), s,
                               prefix=prefix, clean_rows=keep).float()
            x = x + dt * self._velocity(out, x, t)
        return torch.where(rows, env, policy._env_actions(x))                          # the committed rows exact

    def _velocity(self, out: Tensor, x: Tensor, t: float | Tensor) -> Tensor:
        """The head's output as a velocity, as `ActionDecoderPolicy._flow_net` makes it."""
        if self.policy.config.flow_prediction == "velocity":
            return out
        return velocity_from_sample(x, t if isinstance(t, Tensor) else torch.tensor(t, device=x.device), out)


def _example_inputs(policy: "ActionDecoderPolicy", batch: int, context_length: Optional[int],
                    rtc: bool = False) -> dict:
    """Inputs (name → example tensor) the exported graph takes, in its order."""
    cfg = policy.config
    inputs = {STATE: torch.zeros(batch, cfg.state_dim), NOISE: torch.zeros(batch, cfg.action_chunk_size, cfg.action_dim)}
    if cfg.context_dim is not None and context_length:
        inputs[CONTEXT] = torch.zeros(batch, context_length, cfg.context_dim)
        inputs[CONTEXT_MASK] = torch.ones(batch, context_length, dtype=torch.bool)
    if cfg.uses_cameras:
        inputs[IMAGES] = torch.zeros(batch, len(cfg.cameras), 3, cfg.image_size, cfg.image_size, dtype=torch.uint8)
    if rtc:
        inputs[COMMITTED] = torch.zeros(batch, cfg.rtc_max_delay, cfg.action_dim)
        inputs[DELAY] = torch.full((batch,), cfg.rtc_max_delay, dtype=torch.int64)
    return inputs


def default_context_length(policy: "ActionDecoderPolicy") -> Optional[int]:
    """1 for a multi-task policy (its one-hot task token), None (no context input) otherwise."""
    cfg = policy.config
    tasks = cfg.extra.get("tasks")
    return 1 if cfg.context_dim is not None and isinstance(tasks, (list, tuple)) and len(tasks) > 1 else None


def export_onnx(policy: "ActionDecoderPolicy", path: str | Path, steps: Optional[int] = None, batch_size: int = 1,
                sampler: Optional[str] = None, context_length: Optional[int] = -1,
                exporter: str = "torchscript", rtc: bool = False) -> Path:
    """Write the policy's deterministic sampler as one ONNX graph (see `ChunkSampler`) to `path`.

    `steps`: K (None: the checkpoint's `num_inference_timesteps`); `batch_size`: rows per call, fixed
    in the graph (0: any batch size); `sampler`: "ode" (None: the checkpoint's) or "euler" ("sde"
    is refused); `context_length`: L context tokens per row (-1: 1 for a multi-task policy, else no
    context input; None or 0: no context input); `exporter`: "torchscript" (the default) or "dynamo"
    (`torch.onnx.export(dynamo=True)`, slower to export). Inputs are named `observation.state` [B, S],
    `noise` [B, H, D], then `context` [B, L, C] with `context_mask` [B, L] (bool) and
    `observation.images` [B, N_cam, 3, S, S] (uint8) where they apply; the output `action` [B, H, D].
    `rtc`: trained real-time chunking (`ChunkSampler`; checkpoints trained with `rtc_max_delay` M): two
    more inputs, `committed_actions` [B, M, D] (env units) and `delay` [B] (int64, 0..M).
    """
    from . import __version__

    cfg = policy.config
    if exporter not in EXPORTERS:
        raise ValueError(f"exporter: expected one of {list(EXPORTERS)}, got {exporter!r}")
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 0:
        raise ValueError(f"batch_size: expected a non-negative integer (0: any batch size), got {batch_size!r}")
    if context_length == -1:
        context_length = default_context_length(policy)
    if context_length:
        if cfg.context_dim is None:
            raise ValueError(f"context_length: this policy has context_dim=None (no context tokens), got {context_length}")
        if isinstance(context_length, bool) or not isinstance(context_length, int) or context_length < 0:
            raise ValueError(f"context_length: expected a non-negative number of context tokens, got {context_length!r}")
    path = Path(path)
    if path.suffix != ".onnx":
        raise ValueError(f"path: expected a file name ending in .onnx, got {str(path)!r}")
    if not isinstance(rtc, bool):
        raise ValueError(f"rtc: expected True or False, got {rtc!r}")
    module = ChunkSampler(policy, sampler, steps, rtc=rtc).eval()
    inputs = _example_inputs(policy, batch_size or 2, context_length, rtc)
    names = list(inputs)
    path.parent.mkdir(parents=True, exist_ok=True)
    was_training, attn = policy.training, policy.model.attn_implementation
    policy.eval()
    # The TorchScript exporter has no GQA form of SDPA: the explicit softmax computes the same attention.
    policy.model.attn_implementation = "eager" if exporter == "torchscript" else attn
    try:
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore")
            named, args = _Named(module, names), tuple(inputs.values())
            if exporter == "torchscript":
                dynamic = {n: {0: "batch"} for n in names + [ACTION]} if not batch_size else None
                torch.onnx.export(named, args, str(path), input_names=names, output_names=[ACTION],
                                  opset_version=OPSET, dynamo=False, dynamic_axes=dynamic)
            else:
                dims = None
                if not batch_size:
                    batch = torch.export.Dim("batch", min=1)
                    dims = {"args": tuple({0: batch} for _ in names)}
                program = torch.onnx.export(named, args, input_names=names, output_names=[ACTION],
                                            opset_version=OPSET, dynamo=True, optimize=True,
                                            dynamic_shapes=dims, verbose=False)
                program.save(str(path))
    finally:
        policy.model.attn_implementation = attn
        policy.train(was_training)
    meta = {"format": 1, "library_version": __version__, "exporter": exporter,
            "decoder_type": cfg.decoder_type, "sampler": module.sampler, "steps": module.steps,
            "batch_size": batch_size, "rtc_max_delay": module.max_delay, "inputs": {n: [None if (not batch_size and i == 0) else d
                                                     for i, d in enumerate(t.shape)] for n, t in inputs.items()},
            "input_dtypes": {n: str(t.dtype).removeprefix("torch.") for n, t in inputs.items()},
            "output": ACTION, "chunk": [cfg.action_chunk_size, cfg.action_dim], "config": cfg.to_dict()}
    _write_metadata(path, meta)
    return path


class _Named(nn.Module):
    """`ChunkSampler` over the inputs a graph has, in `names`' order (absent ones are None)."""

    def __init__(self, sampler: ChunkSampler, names: list):
        super().__init__()
        self.sampler, self.names = sampler, list(names)

    def forward(self, *args: Tensor) -> Tensor:
        got = dict(zip(self.names, args))
        return self.sampler(got[STATE], got[NOISE], got.get(CONTEXT), got.get(CONTEXT_MASK), got.get(IMAGES),
                            got.get(COMMITTED), got.get(DELAY))


def _write_metadata(path: Path, meta: dict) -> None:
    import onnx

    model = onnx.load(str(path))
    del model.metadata_props[:]
    entry = model.metadata_props.add()
    entry.key, entry.value = METADATA_KEY, json.dumps(meta)
    onnx.save(model, str(path))


@dataclass
class ExportConfig:
    """Write a checkpoint's deterministic sampler as one ONNX graph (run it with `action_decoder.runtime`)."""

    checkpoint: str
    """A directory written by `save_pretrained` (e.g. outputs/train/final), or a Hub repo id."""
    output: str
    """The ONNX file to write (ends in .onnx)."""
    steps: int = 0
    """Sampling steps K unrolled in the graph (0: the checkpoint's num_inference_timesteps)."""
    batch_size: int = 1
    """Rows per call, fixed in the graph (0: any batch size)."""
    sampler: Optional[Literal["ode", "euler", "sde"]] = None
    """ode or euler (None: the checkpoint's sampler; sde is refused: it draws noise at every step)."""
    context_length: int = -1
    """Context tokens per row (-1: 1 for a multi-task policy, else no context input; 0: none)."""
    exporter: Literal["torchscript", "dynamo"] = "torchscript"
    """torchscript or dynamo (torch.onnx.export(dynamo=True))."""
    rtc: bool = False
    """Take committed actions and a delay as inputs (trained real-time chunking; needs train --rtc-max-delay)."""


def run_export(cfg: ExportConfig) -> Path:
    """`action-decoder export`: load the checkpoint, export it, check the file against PyTorch once."""
    from .policy import ActionDecoderPolicy

    if cfg.steps < 0:
        raise ValueError(f"--steps: expected a positive K, or 0 for the checkpoint's own, got {cfg.steps}")
    if cfg.sampler not in (None, "ode", "euler", "sde"):
        raise ValueError(f"--sampler: expected ode or euler, got {cfg.sampler!r}")
    if cfg.context_length < -1:
        raise ValueError(f"--context-length: expected a number of tokens >= 0 (or -1: automatic), got {cfg.context_length}")
    policy = ActionDecoderPolicy.from_pretrained(cfg.checkpoint)
    refusal = export_refusal(policy, cfg.sampler) or (rtc_refusal(policy, cfg.sampler) if cfg.rtc else None)
    if refusal:
        raise ValueError(refusal)
    path = export_onnx(policy, cfg.output, steps=cfg.steps or None, batch_size=cfg.batch_size, sampler=cfg.sampler,
                       context_length=cfg.context_length if cfg.context_length != 0 else None, exporter=cfg.exporter,
                       rtc=cfg.rtc)
    err = check_export(policy, path)
    meta = json.loads(_read_metadata(path))
    print(f"wrote {path}: {meta['decoder_type']} sampler={meta['sampler']} K={meta['steps']} inputs "
          f"{ {k: v for k, v in meta['inputs'].items()} } (max |onnxruntime - PyTorch| = {err:.2e} on a random state)",
          flush=True)
    return path


def _read_metadata(path: Path) -> str:
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return next(p.value for p in model.metadata_props if p.key == METADATA_KEY)


def check_export(policy: "ActionDecoderPolicy", path: str | Path, seed: int = 0) -> float:
    """max |exported − `predict_action_chunk`| (env units) on a random state, noise and inputs (a trained-RTC
    graph: against `sample(prev_chunk=..., delay=..., rtc_mode="trained")` row by row)."""
    from .runtime import OnnxPolicy

    runner = OnnxPolicy(path)
    meta = runner.metadata
    gen = torch.Generator().manual_seed(seed)
    b = runner.batch_size or 2
    inputs = {}
    for name, shape in meta["inputs"].items():
        shape = [b] + shape[1:]
        if name == DELAY:                              # row i commits (M − i) mod (M + 1) actions: row 0 all M
            inputs[name] = (meta["rtc_max_delay"] - torch.arange(b)) % (meta["rtc_max_delay"] + 1)
        elif meta["input_dtypes"][name] == "uint8":
            inputs[name] = torch.randint(0, 256, shape, generator=gen, dtype=torch.uint8)
        elif meta["input_dtypes"][name] == "bool":
            inputs[name] = torch.ones(shape, dtype=torch.bool)
        else:
            inputs[name] = torch.randn(shape, generator=gen)
    stats = policy.normalizers["state"]
    inputs[STATE] = stats.unnormalize(inputs[STATE])          # a state of the data's scale
    batch = {"state": inputs[STATE], "context": inputs.get(CONTEXT), "context_mask": inputs.get(CONTEXT_MASK),
             "images": inputs.get(IMAGES)}
    batch = {k: v for k, v in batch.items() if v is not None}
    rtc = {}
    if DELAY in inputs:
        committed = policy._env_actions(inputs[COMMITTED])                 # actions a chunk could have planned
        inputs[COMMITTED] = committed
        rtc = {"committed": committed.numpy(), "delay": inputs[DELAY].numpy()}
        with torch.no_grad():
            want = torch.cat([policy.sample({k: v[i:i + 1] for k, v in batch.items()}, sampler=meta["sampler"],
                                            steps=meta["steps"], noise=inputs[NOISE][i:i + 1],
                                            prev_chunk=committed[i:i + 1], delay=int(inputs[DELAY][i]),
                                            rtc_mode="trained").actions for i in range(b)])
    else:
        want = policy.predict_action_chunk(batch, sampler=meta["sampler"], steps=meta["steps"], noise=inputs[NOISE],
                                           return_logprob=False)
    got = runner.predict_action_chunk(inputs[STATE].numpy(), inputs[NOISE].numpy(),
                                      context=None if CONTEXT not in inputs else inputs[CONTEXT].numpy(),
                                      context_mask=None if CONTEXT_MASK not in inputs else inputs[CONTEXT_MASK].numpy(),
                                      images=None if IMAGES not in inputs else inputs[IMAGES].numpy(), **rtc)
    return float((torch.from_numpy(got) - want.detach()).abs().max())
