"""Scripted-expert demonstrations on Meta-World, cached on disk as LeRobot v3.0 datasets.

Only successful episodes are kept. An episode is recorded until ``POST_SUCCESS_STEPS``
frames after the first success (or Meta-World's 500-step cap): the chunks that start
near success then hold real actions rather than padding, and the demonstrations stay
short. Attempt ``k`` uses layout seed ``seed·1000 + k`` (``envs.demo_seeds``): seeds draw
disjoint demonstrations, always disjoint from evaluation layouts.

``action_noise`` records demonstrations the DART way (Laskey et al. 2017): the env executes
the expert's action plus Gaussian noise while the dataset keeps the expert's clean action. The
episodes then visit the states a slightly wrong policy reaches, labelled with the expert's
correction, which is what a cloned policy needs to recover from its own errors. A chunking
policy needs more than the next action: the recorded next actions react to noise that comes
after the chunk's first state, which no policy can predict. So each noisy frame also stores
the clean expert's own next ``LOOKAHEAD`` actions from that state (``action.continuation``,
simulated from a saved MuJoCo state and rewound), and chunks are cut from those
(docs/benchmarks/metaworld_bc.md).

``action_label="executed"`` keeps the executed (noisy) action instead, and no continuation: a
chunk's first actions then carry noise the state does not predict, and its later actions are the
expert's reaction to it. With a deterministic expert's clean actions a chunk's first actions are
a function of its state; with executed ones they are not, which is what a committed prefix in
training-time real-time chunking can then inform (docs/benchmarks/rtc.md screens it).

``prefixes`` (`data.perturbed_prefixes`) adds, per demonstration, copies of its frames whose labels
start with a perturbed committed prefix and continue with the expert from where it leads: training
data for training-time real-time chunking (docs/benchmarks/rtc.md).

``cameras`` records pixels too: the named Meta-World cameras (corner2, corner, topview, ...) are
rendered offscreen at every observation (after reset and after each action, aligned with the
states), ``image_size``² pixels, stored as the video features ``observation.images.<camera>``.

``layout="lerobot"`` records what LeRobot's Meta-World env observes instead (`envs.lerobot_view`):
``observation.state`` is the 4-d agent position and, with ``cameras=["corner2"]``,
``observation.image`` its corner2 view at 480² pixels, so that a policy trained on the dataset
runs under ``lerobot-eval --env.type=metaworld``.
"""

from __future__ import annotations

import functools
import importlib.metadata
import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from .episodes import ACTION, CONTINUATION, PREFIX_LENGTH, STATE, EpisodeDataset, concat_datasets
from .lerobot_format import load_dataset
from .lerobot_write import replace_dir, write_episodes
from .perturbed_prefixes import PerturbedPrefixes, perturbed_labels

# The simulator (gymnasium, metaworld, mujoco: the [sim] extra) is imported inside the functions that
# record demonstrations, so that `--dataset` training and `from action_decoder.data import ...` work
# without it.
POST_SUCCESS_STEPS = 10
LOOKAHEAD = 32
"""Clean expert actions stored per noisy frame: enough for chunks of up to 32 actions."""
CACHE_ENV_VAR = "ACTION_DECODER_CACHE"
IMAGE_PREFIX = "observation.images."


@functools.cache
def _rendering() -> str:
    """``MUJOCO_GL``, checked once per process (`check_rendering`), before metaworld imports mujoco."""
    from ..envs.render import check_rendering

    return check_rendering()


def camera_names(cameras, field: str = "--cameras") -> list[str]:
    """Meta-World camera names from ``cameras`` (a list; items may be comma-separated, and may carry
    the feature prefix ``observation.images.``); [] for None."""
    if cameras is None:
        return []
    if isinstance(cameras, str) or not all(isinstance(c, str) for c in cameras):
        raise ValueError(f"{field}: expected a list of Meta-World camera names (e.g. corner2), got {cameras!r}")
    names = [c.strip().removeprefix(IMAGE_PREFIX) for item in cameras for c in item.split(",") if c.strip()]
    if len(set(names)) != len(names):
        raise ValueError(f"{field}: expected distinct camera names, got {names}")
    if names:
        _rendering()               # MUJOCO_GL binds at mujoco's import, which metaworld's brings
    return names


def cache_root() -> Path:
    """``$ACTION_DECODER_CACHE`` if set, else ``~/.cache/action_decoder``."""
    return Path(os.environ.get(CACHE_ENV_VAR) or "~/.cache/action_decoder").expanduser()


def _cache_state(path: Path, num_episodes: int, first_layout: int) -> str:
    """``"complete"``: a v3.0 dataset with all ``num_episodes`` episodes, drawn from today's layouts (before
    SEED_STRIDE, seed s began at layout s); ``"v2.0"``: the same in the older per-episode layout
    (converted in place); ``"missing"`` otherwise (no, partial or stale dataset: recorded anew)."""
    info = path / "meta" / "info.json"
    if not info.exists():
        return "missing"
    meta = json.loads(info.read_text())
    source = meta.get("source", {})
    if meta.get("total_episodes") != num_episodes or source.get("first_layout", source.get("seed")) != first_layout:
        return "missing"
    return {"v3.0": "complete", "v2.0": "v2.0"}.get(meta.get("codebase_version"), "missing")


def _read_v20(path: Path) -> tuple[list[dict], list[str], float, dict]:
    """Episodes, tasks, fps and extra info of a demonstration cache in the v2.0 layout (one
    ``data/chunk-000/episode_000000.parquet`` per episode, jsonl metadata)."""
    import pyarrow.parquet as pq

    info = json.loads((path / "meta" / "info.json").read_text())
    lines = lambda name: [json.loads(x) for x in (path / "meta" / name).read_text().splitlines() if x.strip()]
    tasks = [d["task"] for d in sorted(lines("tasks.jsonl"), key=lambda d: d["task_index"])]
    seeds = {d["episode_index"]: d.get("seed") for d in lines("episodes.jsonl")}
    more = info["features"].get(CONTINUATION, {}).get("shape")                  # [K, D]
    episodes = []
    for file in sorted((path / "data").glob("chunk-*/episode_*.parquet")):
        t = pq.read_table(file)
        vec = lambda k: np.asarray(t[k].to_pylist(), np.float32)                    # [L, W]
        ep = {STATE: vec(STATE), ACTION: vec(ACTION), "task_index": int(t["task_index"][0].as_py()),
              "next.reward": t["next.reward"].to_numpy(), "next.success": t["next.success"].to_numpy(zero_copy_only=False)}
        if more is not None:
            ep[CONTINUATION] = vec(CONTINUATION).reshape(len(ep[ACTION]), *more)   # [L, K, D]
        if seeds.get(int(t["episode_index"][0].as_py())) is not None:
            ep["seed"] = seeds[int(t["episode_index"][0].as_py())]
        episodes.append(ep)
    extra = {k: info[k] for k in ("robot_type", "source") if k in info}
    return episodes, tasks, info["fps"], {**extra, "env": "metaworld"}


ACTION_LABELS = ("expert", "executed")


def check_action_label(action_label: str, action_noise: float) -> None:
    """``action_label`` one of ``ACTION_LABELS``; "executed" only with ``action_noise`` > 0 (else the two agree)."""
    if action_label not in ACTION_LABELS:
        raise ValueError(f"--action-label: expected one of {list(ACTION_LABELS)}, got {action_label!r}")
    if action_label == "executed" and not action_noise > 0:
        raise ValueError(f"--action-label: 'executed' keeps the noisy executed action and needs --action-noise > 0, "
                         f"got --action-noise {action_noise!r}")


def expert_continuation(env, expert, prefix: np.ndarray, obs: np.ndarray | None = None) -> np.ndarray:
    """``[LOOKAHEAD, D]``: the rows of ``prefix [d, D]`` executed from the env's current state, then the
    clean expert's actions from the state they reach (with d = 0, from ``obs``, the current observation);
    the env is left as it was. Past Meta-World's step cap the last action is held."""
    from ..envs.metaworld_tasks import MAX_EPISODE_STEPS, restore_state, save_state

    if len(prefix) == 0 and obs is None:
        raise ValueError("expert_continuation: an empty prefix needs obs, the observation the expert starts from")
    saved, actions, executed = save_state(env), list(prefix) or [expert(obs)], 0
    while len(actions) < LOOKAHEAD and env.unwrapped.curr_path_length < MAX_EPISODE_STEPS:
        obs = env.step(actions[executed])[0]
        executed += 1
        if executed == len(actions):
            actions.append(expert(obs))
    restore_state(env, saved)
    return np.stack(actions + [actions[-1]] * (LOOKAHEAD - len(actions)))


def _rollout(env, expert, seed: int, action_noise: float = 0.0, rig=None, observe=None,
             action_label: str = "expert", prefixes: PerturbedPrefixes | None = None) -> dict | None:
    """One expert episode from layout ``seed``; None if it never succeeds. With ``action_noise``
    the executed action is perturbed (noise drawn from ``seed``); with ``action_label`` "expert" the
    recorded one is not, and each frame keeps the clean continuation; with "executed" the recorded
    action is the executed one. ``prefixes`` adds ``"perturbed"``: ``prefixes.copies`` episodes of the
    same states whose labels start with a perturbed prefix (`perturbed_prefixes`; drawn from
    ``default_rng([seed, 1])``), and gives the episode itself ``action.continuation`` (its own next
    actions, the last held, or the clean continuation) and ``action.prefix_length`` 0, as every
    episode of a dataset has these columns or none. ``rig`` (`envs.render.CameraObservation`) adds the
    frames of its cameras at every recorded state (keys: a camera name, stored as ``observation.images.<name>``,
    or a whole feature key). ``observe`` maps the simulator's state to the recorded one (default: as it is)."""
    from ..envs.metaworld_tasks import MAX_EPISODE_STEPS

    obs = env.reset(seed=seed)[0]
    noise = np.random.default_rng(seed)
    perturb = np.random.default_rng([seed, 1])
    states, actions, continuations, rewards, successes, first_success = [], [], [], [], [], None
    clean_actions, perturbed = [], []            # the expert's own actions so far; per frame, its perturbed labels
    frames: dict[str, list[np.ndarray]] = {}
    while len(actions) < MAX_EPISODE_STEPS:
        action = expert(obs)                                                   # [D], in [-1, 1]
        states.append(observe(obs) if observe is not None else obs.astype(np.float32))
        for camera, frame in (rig(env) if rig is not None else {}).items():   # [S, S, 3] uint8
            frames.setdefault(camera if camera.startswith("observation.") else IMAGE_PREFIX + camera, []).append(frame)
        clean = action
        if action_noise > 0 and action_label == "expert":
            continuations.append(expert_continuation(env, expert, action[None]))   # [LOOKAHEAD, D]
        if prefixes is not None:
            plan = continuations[-1] if continuations else expert_continuation(env, expert, action[None])
            perturbed.append(perturbed_labels(np.array(clean_actions, np.float32), plan, prefixes, perturb,
                                              lambda prefix: expert_continuation(env, expert, prefix)))
            clean_actions.append(clean)
        if action_noise > 0:
            action = np.clip(action + action_noise * noise.standard_normal(action.shape), -1.0, 1.0)
        actions.append(clean if action_label == "expert" else action)
        obs, reward, _, _, info = env.step(action.astype(np.float32))
        rewards.append(reward)
        successes.append(bool(info["success"]))
        if successes[-1] and first_success is None:
            first_success = len(actions) - 1
        if first_success is not None and len(actions) > first_success + POST_SUCCESS_STEPS:
            break
    if first_success is None:
        return None
    episode = {STATE: np.stack(states), ACTION: np.stack(actions), "task_index": 0,
               "next.reward": np.asarray(rewards), "next.success": np.asarray(successes), "seed": seed}
    if frames:
        episode["images"] = {k: np.stack(v) for k, v in frames.items()}               # [L, S, S, 3]
    if continuations:
        episode[CONTINUATION] = np.stack(continuations)                               # [L, LOOKAHEAD, D]
    if prefixes is not None:
        n = len(actions)
        if not continuations:
            follow = np.minimum(np.arange(n)[:, None] + np.arange(LOOKAHEAD), n - 1)   # [L, LOOKAHEAD]
            episode[CONTINUATION] = episode[ACTION][follow]
        episode[PREFIX_LENGTH] = np.zeros(n, np.int64)
        copies = []
        for c in range(prefixes.copies):
            labels = np.stack([frame[c][0] for frame in perturbed])                  # [L, LOOKAHEAD, D]
            copies.append({**{k: v for k, v in episode.items() if k not in (ACTION, CONTINUATION, PREFIX_LENGTH)},
                           ACTION: labels[:, 0], CONTINUATION: labels,
                           PREFIX_LENGTH: np.array([frame[c][1] for frame in perturbed], np.int64)})
        episode["perturbed"] = copies
    return episode


def record_episodes(
    task: str, num_episodes: int, seed: int = 0, max_attempts_factor: float = 3.0, action_noise: float = 0.0,
    cameras: list[str] | None = None, image_size: int = 64, layout: str = "library", action_label: str = "expert",
    prefixes: PerturbedPrefixes | None = None,
) -> tuple[list[dict], float, dict]:
    """Roll out the scripted expert of ``task`` until ``num_episodes`` succeed: the episodes (the
    dicts ``write_episodes`` takes, ``task_index`` 0, ``images`` of ``cameras`` at ``image_size``²
    when given), the env's fps and a ``source`` record (env, versions, seed, first layout,
    attempts, expert success rate, noise, label). ``action_label``: the action kept with ``action_noise`` > 0,
    "expert" (clean, with the continuation) or "executed" (the noisy one). ``layout="lerobot"``: LeRobot's observation
    (`envs.lerobot_view`; ``cameras`` None or ["corner2"], at LeRobot's 480² whatever ``image_size``).
    ``prefixes`` (`perturbed_prefixes`) adds ``prefixes.copies`` episodes per demonstration after the
    demonstrations, each with its demonstration's states (and camera frames) and perturbed-prefix labels."""
    cameras = camera_names(cameras)
    from ..envs import lerobot_view
    from ..envs.metaworld_tasks import SEED_STRIDE, canonical_task, demo_seeds, expert_policy, make_env
    from ..envs.render import CameraObservation

    if layout not in ("library", "lerobot"):
        raise ValueError(f"--layout: expected 'library' or 'lerobot', got {layout!r}")
    check_action_label(action_label, action_noise)
    if layout == "lerobot" and cameras not in ([], [lerobot_view.CAMERA]):
        raise ValueError(f"--cameras: LeRobot's Meta-World env observes its {lerobot_view.CAMERA} camera only; expected "
                         f"--cameras {lerobot_view.CAMERA} (or none, a state-only dataset) with --layout lerobot, "
                         f"got {cameras}")

    name = canonical_task(task)
    if not isinstance(num_episodes, (int, np.integer)) or num_episodes < 1:
        raise ValueError(f"num_episodes: expected an integer >= 1, got {num_episodes!r}")
    if not max_attempts_factor >= 1:
        raise ValueError(f"max_attempts_factor: expected a number >= 1, got {max_attempts_factor!r}")
    if not (isinstance(action_noise, (int, float)) and 0 <= action_noise <= 1):
        raise ValueError(f"action_noise: expected a standard deviation in [0, 1] (actions span [-1, 1]), "
                         f"got {action_noise!r}")
    attempts = math.ceil(num_episodes * max_attempts_factor)
    if attempts > SEED_STRIDE:
        raise ValueError(f"num_episodes: expected at most {int(SEED_STRIDE // max_attempts_factor)} demonstrations "
                         f"per seed ({max_attempts_factor:g} attempts each within the seed's {SEED_STRIDE} layouts), "
                         f"got {num_episodes}")
    seeds = demo_seeds(seed, attempts)
    observe = None
    if layout == "lerobot":
        rig, observe, image_size = (lerobot_view.LeRobotCamera() if cameras else None), lerobot_view.agent_pos, \
            lerobot_view.IMAGE_SIZE
    else:
        rig = CameraObservation(cameras, image_size, "--cameras") if cameras else None
    env, expert, episodes = make_env(name, seed), expert_policy(name), []
    try:
        for attempt, layout_seed in enumerate(seeds, start=1):
            episode = _rollout(env, expert, layout_seed, action_noise, rig, observe, action_label, prefixes)
            if episode is not None:
                episodes.append(episode)
            if len(episodes) == num_episodes:
                break
    finally:
        if rig is not None:
            rig.close()
        env.close()
    if len(episodes) < num_episodes:
        raise ValueError(
            f"--demos: the scripted expert of {name} succeeded in {len(episodes)} of {len(seeds)} attempts (layouts "
            f"of --seed {seed}, max_attempts_factor {max_attempts_factor:g}), fewer than the {num_episodes} "
            f"demonstrations asked for; ask for fewer, try another --seed"
            + (f" or lower the recording noise (now {action_noise:g}: record's --action-noise, train's "
               f"--demo-noise)" if action_noise > 0 else "")
        )
    source = {"env": "metaworld", "metaworld_version": importlib.metadata.version("metaworld"), "task": name,
              "seed": seed, "first_layout": seeds[0], "attempts": attempt, "expert_success_rate": num_episodes / attempt,
              "post_success_steps": POST_SUCCESS_STEPS, "action_noise": action_noise,
              **({"action_label": action_label} if action_label != "expert" else {}),
              **({"cameras": cameras, "image_size": image_size} if cameras else {}),
              **({"layout": layout} if layout != "library" else {}),
              **({"perturbed_prefixes": prefixes.record()} if prefixes is not None else {})}
    copies = [copy for episode in episodes for copy in episode.pop("perturbed", [])]
    return episodes + copies, round(1.0 / env.unwrapped.dt, 6), source


def generate_demos(
    task: str,
    num_episodes: int,
    seed: int = 0,
    max_attempts_factor: float = 3.0,
    cache_dir: str | Path | None = None,
    action_noise: float = 0.0,
    cameras: list[str] | None = None,
    image_size: int = 64,
    prefixes: PerturbedPrefixes | None = None,
) -> Path:
    """Directory holding ``num_episodes`` successful expert episodes of ``task`` as a LeRobot v3.0
    dataset, recorded with ``action_noise`` (std of the Gaussian added to each executed action;
    0: clean rollouts), with the frames of ``cameras`` (Meta-World names) at ``image_size``² and, with
    ``prefixes``, their perturbed-prefix copies (`record_episodes`).

    Reuses ``<cache>/metaworld/<task>-n<N>-s<seed>[-dart<σ>][-cam<a+b>-px<size>][-pp…]`` when complete. A complete cache in
    the older v2.0 layout is converted in place (same episodes, no simulator run), saying so in one
    line; anything else is recorded anew. New datasets are written into a temporary sibling and
    renamed into place (concurrent runs never see a partial dataset). Raises ValueError if
    ``ceil(N * max_attempts_factor)`` attempts do not yield N successes.
    """
    cameras = camera_names(cameras)
    from ..envs.metaworld_tasks import canonical_task, demo_seeds

    name = canonical_task(task)
    if not (isinstance(action_noise, (int, float)) and 0 <= action_noise <= 1):
        raise ValueError(f"action_noise: expected a standard deviation in [0, 1] (actions span [-1, 1]), "
                         f"got {action_noise!r}")
    suffix = (f"-dart{action_noise:g}" if action_noise > 0 else "") + \
        (f"-cam{'+'.join(cameras)}-px{image_size}" if cameras else "") + (prefixes.suffix() if prefixes else "")
    final = Path(cache_dir or cache_root()).expanduser() / "metaworld" / f"{name}-n{num_episodes}-s{seed}{suffix}"
    stored = num_episodes * (1 + (prefixes.copies if prefixes else 0))          # demonstrations and their copies
    state = _cache_state(final, stored, demo_seeds(seed, 1)[0]) if isinstance(num_episodes, (int, np.integer)) else "missing"
    if state == "complete":
        return final
    if state == "v2.0":
        try:
            episodes, tasks, fps, extra = _read_v20(final)
            print(f"demonstrations: converting the cache {final} from LeRobot layout v2.0 to v3.0", flush=True)
        except (OSError, ValueError, KeyError, TypeError, IndexError) as err:   # pyarrow's errors are ValueErrors
            print(f"demonstrations: the v2.0 cache {final} cannot be converted ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
                  f"recording it anew", flush=True)
            state = "missing"
    if state != "v2.0":
        episodes, fps, source = record_episodes(name, num_episodes, seed, max_attempts_factor, action_noise,
                                                cameras, image_size, prefixes=prefixes)
        tasks, extra = [name], {"robot_type": "sawyer", "env": "metaworld", "source": source}
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=final.parent))
    write_episodes(tmp, episodes, tasks, fps, extra)
    replace_dir(tmp, final)
    return final


def record_demos(spec: str, num_episodes: int, output_dir: str | Path, seed: int = 0, action_noise: float = 0.0,
                 max_attempts_factor: float = 3.0, cameras: list[str] | None = None, image_size: int = 64,
                 layout: str = "library", action_label: str = "expert",
                 prefixes: PerturbedPrefixes | None = None) -> Path:
    """Record ``num_episodes`` expert demonstrations of every task in ``spec`` (``metaworld/<task>``,
    comma-separated or a group) into one LeRobot v3.0 dataset at ``output_dir``, with the
    Meta-World task names as task strings (``task_index`` in the order of ``resolve_tasks``) and
    ``"env": "metaworld"`` in ``info.json``; ``cameras`` (Meta-World names) add their frames at
    ``image_size``² as video features ``observation.images.<camera>``. ``layout="lerobot"`` records
    LeRobot's Meta-World observation instead (`record_episodes`), with ``"layout": "lerobot"`` in
    ``info.json``. ``action_label`` (`record_episodes`): the action kept with ``action_noise`` > 0;
    ``prefixes``: each demonstration's perturbed-prefix copies (`record_episodes`).
    ``output_dir`` must be new or empty: an existing dataset is never overwritten."""
    cameras = camera_names(cameras)
    check_action_label(action_label, action_noise)
    from ..envs.metaworld_tasks import resolve_tasks

    out = Path(output_dir).expanduser()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise ValueError(f"--output-dir: expected a new or empty directory, got {out} (not empty)")
    names, episodes, sources = resolve_tasks(spec), [], {}
    for i, name in enumerate(names):
        eps, fps, sources[name] = record_episodes(name, num_episodes, seed, max_attempts_factor, action_noise,
                                                  cameras, image_size, layout, action_label, prefixes)
        episodes += [{**ep, "task_index": i} for ep in eps]
    source = sources[names[0]] if len(names) == 1 else {"env": "metaworld", "tasks": sources}
    info = {"robot_type": "sawyer", "env": "metaworld", "source": source}
    if layout == "lerobot":
        from ..envs.lerobot_view import STATE_NAMES

        return write_episodes(out, episodes, names, fps, {**info, "layout": layout}, names={STATE: STATE_NAMES})
    return write_episodes(out, episodes, names, fps, info)


def load_demos(spec: str, num_episodes: int, seed: int = 0, action_noise: float = 0.0,
               cameras: list[str] | None = None, image_size: int = 64,
               prefixes: PerturbedPrefixes | None = None) -> EpisodeDataset:
    """Expert demonstrations of every task in ``spec`` (generated or cached), concatenated;
    ``task_index`` follows the order of ``resolve_tasks(spec)``. ``cameras`` (Meta-World names, e.g.
    ``["corner2"]``; None: none) adds ``images`` ``observation.images.<camera>`` of ``image_size``²;
    ``prefixes`` their perturbed-prefix copies (`record_episodes`)."""
    cameras = camera_names(cameras)
    from ..envs.metaworld_tasks import resolve_tasks

    keys = [IMAGE_PREFIX + c for c in cameras]
    return concat_datasets([load_dataset(generate_demos(t, num_episodes, seed, action_noise=action_noise,
                                                        cameras=cameras, image_size=image_size, prefixes=prefixes),
                                         keys)
                            for t in resolve_tasks(spec)])
