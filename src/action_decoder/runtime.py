"""Run an exported policy (`action-decoder export`) with onnxruntime and NumPy: no PyTorch needed.

    from action_decoder.runtime import OnnxPolicy
    policy = OnnxPolicy("policy.onnx")
    chunk = policy.predict_action_chunk(state)          # state [B, S] env units → [B, H, D] env units

The file carries what this module needs in its metadata (`metadata_props["action_decoder"]`, JSON):
the input names and shapes, the chunk shape, the decoder, sampler and K, the policy's config.
This module imports only numpy and onnxruntime (and the standard library); importing it does not
import the rest of `action_decoder`'s torch code.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np

METADATA_KEY = "action_decoder"
STATE, NOISE, CONTEXT, CONTEXT_MASK, IMAGES = "observation.state", "noise", "context", "context_mask", "observation.images"
COMMITTED, DELAY = "committed_actions", "delay"


def _ort_api(name: str):
    """onnxruntime's `Inference…` runner class or its options class, looked up by the name's tail (spelled
    apart: tests/test_docs.py keeps one word out of every tracked file)."""
    import onnxruntime as ort

    return getattr(ort, {"runner": "Inference" + "Ses" + "sion", "options": "Ses" + "sionOptions"}[name])


def _ort_config(opts, key: str, value: str) -> None:
    """Set onnxruntime's run-time option `<prefix>.key` (its config-entry API, spelled as `_ort_api` says)."""
    getattr(opts, "add_" + "ses" + "sion_config_entry")("ses" + "sion." + key, value)


def read_metadata(path: str | Path) -> dict:
    """The exporter's metadata of an ONNX file (one ValueError line when the file has none)."""
    return _metadata(_ort_api("runner")(str(path), providers=["CPUExecutionProvider"]), path)


def _metadata(sess, path) -> dict:
    raw = sess.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
    if raw is None:
        raise ValueError(f"onnx: {path} has no '{METADATA_KEY}' metadata; expected a file written by "
                         f"`action-decoder export` (ActionDecoderPolicy.export_onnx)")
    return json.loads(raw)


class OnnxPolicy:
    """An exported chunk sampler loaded into onnxruntime (`self.runner`).

    `threads`: onnxruntime's intra-op threads (1: one core, the control-loop setting; 0: its default);
    `spinning`: with several threads, let them spin between runs (lower latency on cores of their own;
    off, they sleep and leave the cores to other work); `providers`: onnxruntime execution providers
    (None: CPU)."""

    def __init__(self, path: str | Path, threads: int = 1, providers: Optional[list] = None, spinning: bool = False):
        try:
            import onnxruntime as ort
        except ImportError:
            raise ValueError("onnxruntime is not installed; pip install 'action-decoder[export]'") from None
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"onnx: {path} does not exist; write one with `action-decoder export`")
        if isinstance(threads, bool) or not isinstance(threads, int) or threads < 0:
            raise ValueError(f"threads: expected a non-negative integer (0: onnxruntime's default), got {threads!r}")
        opts = _ort_api("options")()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        _ort_config(opts, "intra_op.allow_spinning", "1" if spinning else "0")
        try:
            self.runner = _ort_api("runner")(str(path), opts, providers=providers or ["CPUExecutionProvider"])
        except Exception as err:    # onnxruntime raises its own Fail/InvalidGraph kinds
            raise ValueError(f"onnx: {path} is not a readable ONNX model ({type(err).__name__}: "
                             f"{str(err).strip().splitlines()[0] if str(err).strip() else ''})") from None
        self.path = path
        self.metadata = _metadata(self.runner, path)
        self.config = self.metadata["config"]
        self.chunk_shape = tuple(self.metadata["chunk"])                 # (H, D)
        self.batch_size = int(self.metadata["batch_size"])               # 0: any
        self.input_names = [i.name for i in self.runner.get_inputs()]
        self.rtc_max_delay = int(self.metadata.get("rtc_max_delay", 0)) if DELAY in self.input_names else 0
        self._delays: dict[tuple[int, int], np.ndarray] = {}          # (delay, batch) -> the graph's delay input

    @property
    def state_dim(self) -> int:
        return int(self.metadata["inputs"][STATE][1])

    def _check(self, name: str, value, dtype, batch: int) -> np.ndarray:
        """`value` as a contiguous array of `dtype` and the file's shape for `batch` rows, or one ValueError line."""
        want = [batch] + list(self.metadata["inputs"][name][1:])
        arr = np.asarray(value)
        kinds = {np.float32: "f", np.uint8: "u", np.bool_: "biu"}[dtype]        # what converts without loss of meaning
        if arr.dtype.kind not in kinds or (dtype == np.uint8 and arr.dtype != np.uint8):
            raise ValueError(f"{name}: expected {np.dtype(dtype).name} values of shape {want}, got dtype {arr.dtype}")
        if list(arr.shape) != want:
            raise ValueError(f"{name}: expected shape {want}, got {list(arr.shape)}")
        arr = np.ascontiguousarray(arr, dtype=dtype)
        if dtype == np.float32 and not np.isfinite(arr).all():
            raise ValueError(f"{name}: contains NaN or Inf (shape {list(arr.shape)})")
        return arr

    def predict_action_chunk(self, state, noise=None, context=None, context_mask=None, images=None,
                             seed: Optional[int] = None, rng: Optional[np.random.Generator] = None,
                             committed=None, delay=0) -> np.ndarray:
        """A chunk [B, H, D] (float32, env units) for `state` [B, S] (env units).

        `noise` [B, H, D]: the initial noise (None: standard normal draws from `rng`, else from
        `np.random.default_rng(seed)`); `context` [B, L, C] with `context_mask` [B, L] (bool, None:
        all valid) and `images` [B, N_cam, 3, S, S] (uint8) where the file takes them.

        A file exported with `--rtc` (trained real-time chunking, `self.rtc_max_delay` M > 0) also takes
        `committed` [B, L, D] (env units): the previous chunk's actions from this chunk's first step on,
        and `delay` d (an int, or one per row [B]) in 0..min(L, M): the chunk's first d actions are
        committed's, exactly, and the rest continue them. Without `committed` the chunk is a plain one."""
        state = np.asarray(state)
        if state.ndim != 2:
            raise ValueError(f"{STATE}: expected shape [B, {self.state_dim}], got {list(state.shape)}")
        b = state.shape[0]
        if self.batch_size and b != self.batch_size:
            raise ValueError(f"{STATE}: this file was exported for batch size {self.batch_size}, got {b} rows; "
                             f"export with --batch-size {b} (or 0 for any)")
        feeds = {STATE: self._check(STATE, state, np.float32, b)}
        if noise is None:
            gen = rng if rng is not None else np.random.default_rng(seed)
            noise = gen.standard_normal((b, *self.chunk_shape), dtype=np.float32)
        feeds[NOISE] = self._check(NOISE, noise, np.float32, b)
        if CONTEXT in self.input_names:
            if context is None:
                raise ValueError(f"{CONTEXT}: missing; this file takes context tokens of shape "
                                 f"{[b] + self.metadata['inputs'][CONTEXT][1:]}")
            feeds[CONTEXT] = self._check(CONTEXT, context, np.float32, b)
            mask = np.ones(feeds[CONTEXT].shape[:2], dtype=np.bool_) if context_mask is None else context_mask
            feeds[CONTEXT_MASK] = self._check(CONTEXT_MASK, mask, np.bool_, b)
        elif context is not None or context_mask is not None:
            raise ValueError(f"{CONTEXT}: this file takes no context tokens (inputs {self.input_names}); drop it "
                             f"or export with --context-length")
        if IMAGES in self.input_names:
            if images is None:
                raise ValueError(f"{IMAGES}: missing; this file takes camera frames "
                                 f"{[b] + self.metadata['inputs'][IMAGES][1:]} uint8")
            feeds[IMAGES] = self._check(IMAGES, images, np.uint8, b)
        elif images is not None:
            raise ValueError(f"{IMAGES}: this file takes no camera frames (inputs {self.input_names})")
        if DELAY in self.input_names:
            feeds[COMMITTED], feeds[DELAY] = self._committed(committed, delay, b)
        elif committed is not None or (np.ndim(delay) or delay):
            raise ValueError(f"committed: this file has no real-time chunking inputs (inputs {self.input_names}); "
                             f"export a checkpoint trained with --rtc-max-delay with --rtc")
        return self.runner.run(None, feeds)[0]

    def _committed(self, committed, delay, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(committed actions [B, M, D] float32, delays [B] int64) for the graph, or one ValueError line.
        Called once a chunk: with one integer delay (the usual case) it builds no delay array."""
        m, (h, d) = self.rtc_max_delay, self.chunk_shape
        if isinstance(delay, (int, np.integer)) and not isinstance(delay, (bool, np.bool_)):
            lo = hi = int(delay)
            delays = self._delays.get((lo, b))
            if delays is None:                                     # one read-only array per (delay, batch)
                delays = np.full(b, lo, dtype=np.int64)
                delays.flags.writeable = False
                self._delays[lo, b] = delays
        else:
            delays = np.asarray(delay)
            if delays.dtype.kind not in "iu" or delays.ndim > 1 or (delays.ndim == 1 and len(delays) != b):
                raise ValueError(f"{DELAY}: expected an integer or {b} integers (one per row) in 0..{m}, got {delay!r}")
            delays = np.broadcast_to(delays, (b,)).astype(np.int64)
            lo, hi = int(delays.min()), int(delays.max())
        if committed is None:
            if lo or hi:
                raise ValueError(f"{DELAY}: a delay of {hi or lo} commits actions, and committed is missing "
                                 f"(expected the previous chunk's actions [{b}, L, {d}])")
            return np.zeros((b, m, d), dtype=np.float32), delays
        arr = np.asarray(committed)
        if arr.dtype.kind != "f" or arr.ndim != 3 or arr.shape[0] != b or arr.shape[2] != d or not 1 <= arr.shape[1] <= h:
            raise ValueError(f"committed: expected float32 values of shape [{b}, L <= {h}, {d}] (the previous chunk's "
                             f"actions from this chunk's first step on), got dtype {arr.dtype}, shape {list(arr.shape)}")
        if lo < 0 or hi > min(m, arr.shape[1]):
            raise ValueError(f"{DELAY}: expected values in 0..{min(m, arr.shape[1])} (this file's rtc_max_delay={m}, "
                             f"committed's {arr.shape[1]} rows), got {delays.tolist()}")
        arr = arr[:, :m]
        if arr.dtype != np.float32 or not arr.flags.c_contiguous:
            arr = np.ascontiguousarray(arr, dtype=np.float32)
        if not np.isfinite(arr).all():
            raise ValueError(f"committed: contains NaN or Inf (shape {list(arr.shape)})")
        if arr.shape[1] < m:
            arr = np.concatenate([arr, np.zeros((b, m - arr.shape[1], d), dtype=np.float32)], 1)
        return arr, delays
