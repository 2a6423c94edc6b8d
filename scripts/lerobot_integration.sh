#!/usr/bin/env bash
# LeRobot interop, end to end, in a virtual environment with LeRobot (0.4.4 or 0.6.x) and this repository.
#
#   scripts/lerobot_integration.sh            # builds (or reuses) the venv, then runs every step
#   LEROBOT_VENV=/path/to/venv WORK_DIR=/tmp/x scripts/lerobot_integration.sh
#   LEROBOT_VERSION=0.6.1 LEROBOT_PYTHON=python3.12 LEROBOT_VENV=.cache/lerobot06-venv scripts/lerobot_integration.sh
#
# A new venv gets lerobot==$LEROBOT_VERSION (0.4.4) under $LEROBOT_PYTHON (python3; LeRobot >= 0.5
# needs Python >= 3.12); a venv that already has LeRobot keeps the version it has.
#
# Steps: (a) write a dataset with LeRobot's API; (b) `action-decoder train --dataset` on it;
# (c) `action-decoder record` a Meta-World dataset and load it with `LeRobotDataset`;
# (d) `lerobot-train --policy.type=action_decoder` for DDPM, flow matching and MeanFlow;
# (e) reload each checkpoint with LeRobot's `from_pretrained` and run `select_action`; MeanFlow
# again with 2 data-parallel processes (torchrun → accelerate, gloo on CPU);
# (f) the plugin's unit tests with LeRobot installed; (i) `action-decoder serve` on loopback with
# LeRobot's own RobotClient and a simulated robot (tests/test_serve_lerobot.py: MF-1 (eager and compiled) and FM-10 chunks,
# real-time chunking; about two minutes); closed loop on LeRobot's Meta-World env:
# (g) a state policy trained by `action-decoder train` on `record --layout lerobot` data, converted
# (`action-decoder convert --to lerobot`) and evaluated by `lerobot-eval --env.type=metaworld`,
# within 10 points of `action-decoder eval` on the same task and episode count; (h) a camera
# policy trained by `lerobot-train` on `record --layout lerobot --cameras corner2` data and
# evaluated by `lerobot-eval` (its success is reported). One summary line per step (ok/FAILED);
# exit 1 if any step failed. Building the venv takes about 5 minutes and 8.7 GB (LeRobot
# brings its own torch: < 2.11 for 0.4.4, < 2.12 for 0.6.1). Steps a-f take a few minutes on a CPU; g and h render LeRobot's
# 480-px camera at every step (about 0.6 s a frame on a CPU): tens of minutes. Nothing is pushed.
#   MW_TASK (door-close), MW_EPISODES (10), MW_DEMOS (10), MW_TRAIN_STEPS (800): step g;
#   CAM_DEMOS (5), CAM_STEPS (200), CAM_EPISODES (2): step h; LEROBOT_SKIP_CLOSED_LOOP=1 skips g and h.
set -uo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=${LEROBOT_VENV:-$REPO/.cache/lerobot-venv}   # .cache/ is git-ignored
WORK=${WORK_DIR:-$(mktemp -d -t lerobot_integration.XXXXXX)}
STEPS=${LEROBOT_STEPS:-20}
MW_TASK=${MW_TASK:-door-close} MW_EPISODES=${MW_EPISODES:-10} MW_DEMOS=${MW_DEMOS:-10} MW_TRAIN_STEPS=${MW_TRAIN_STEPS:-800}
CAM_DEMOS=${CAM_DEMOS:-5} CAM_STEPS=${CAM_STEPS:-200} CAM_EPISODES=${CAM_EPISODES:-2}
PY=$VENV/bin/python
mkdir -p "$WORK/logs"
# This checkout's code first, whatever the venv has installed; no network, no W&B, one thread.
export PYTHONPATH="$REPO/src:$REPO/lerobot_policy_action_decoder/src${PYTHONPATH:+:$PYTHONPATH}"
export HF_HUB_OFFLINE=1 HF_DATASETS_OFFLINE=1 WANDB_MODE=disabled OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
export PATH="$VENV/bin:$PATH" MUJOCO_GL=${MUJOCO_GL:-egl}

SUMMARY=()
FAILED=0
step() {  # step NAME COMMAND...: run, log to $WORK/logs/NAME.log, record one summary line
  local name=$1; shift
  local start=$SECONDS
  if "$@" >"$WORK/logs/$name.log" 2>&1; then
    SUMMARY+=("ok      $name ($((SECONDS - start)) s)")
  else
    FAILED=1
    SUMMARY+=("FAILED  $name ($((SECONDS - start)) s): $(grep -v '^\s*$' "$WORK/logs/$name.log" | tail -1 | cut -c1-160) [log: $WORK/logs/$name.log]")
  fi
}

setup_venv() {
  if ! "$PY" -c "import lerobot" 2>/dev/null; then
    "${LEROBOT_PYTHON:-python3}" -m venv "$VENV" && "$VENV/bin/pip" install "lerobot==${LEROBOT_VERSION:-0.4.4}" || return 1
  fi
  # The installed LeRobot stays; from 0.6 on its dataset reader (datasets, PyAV) and lerobot-train's
  # accelerate are its `training` extra.
  local pin
  pin=$("$PY" -c "import lerobot; from packaging.version import Version as V; v = lerobot.__version__; \
print(f'lerobot[training]=={v}' if V(v) >= V('0.6') else f'lerobot=={v}')") || return 1
  # The core and the plugin without their dependencies (the venv's torch stays LeRobot's), then
  # the core's other dependencies, resolved together with lerobot's pins and torch held at the
  # installed version (transformers is left out: the core does not import it, and a newer one
  # would replace the huggingface-hub that lerobot 0.4.4 needs).
  "$VENV/bin/pip" install --no-deps -e "$REPO" -e "$REPO/lerobot_policy_action_decoder" || return 1
  "$PY" -c "import torch; print('torch==' + torch.__version__.split('+')[0])" > "$WORK/constraints.txt"
  # The core's dependencies are read from its pyproject.toml (all but torch), so this list cannot drift.
  mapfile -t deps < <("$PY" -c "import sys, tomllib, re; deps = tomllib.load(open(sys.argv[1], 'rb'))['project']['dependencies']; \
print('\n'.join(d for d in deps if re.split('[<>=!~ ;]', d)[0] != 'torch'))" "$REPO/pyproject.toml")
  "$VENV/bin/pip" install -c "$WORK/constraints.txt" "$pin" "${deps[@]}" pytest || return 1
  # grpcio for `action-decoder serve` and LeRobot's RobotClient (step i): LeRobot's async extra.
  "$PY" -c "import grpc" 2>/dev/null || "$VENV/bin/pip" install -c "$WORK/constraints.txt" \
      "$("$PY" -c "import lerobot; print(f'lerobot[async]=={lerobot.__version__}')")" || return 1
  # Meta-World for `action-decoder record` and LeRobot's Meta-World env (steps c, g, h; imageio for the
  # rendering check of step f). Not "lerobot[metaworld]": it brings mujoco 4, with which metaworld 3.0
  # fails ("could not broadcast").
  "$VENV/bin/pip" install -c "$WORK/constraints.txt" "$pin" "metaworld>=3.0" "mujoco>=3.0,<4" "imageio>=2.28" \
      "imageio_ffmpeg>=0.5.1" \
      || echo "metaworld not installed: steps c, g and h will fail"
  "$PY" -c "import lerobot, torch, action_decoder, lerobot_policy_action_decoder as p; p.ActionDecoderPolicy; \
print('lerobot', lerobot.__version__, 'torch', torch.__version__)"
}

no_env_eval() {  # lerobot-train's flag that turns off evaluation in an env: eval_freq (to 0.5), env_eval_freq (0.6 on)
  "$PY" -c "import dataclasses; from lerobot.configs.train import TrainPipelineConfig as T; \
print('--env_eval_freq=0' if 'env_eval_freq' in {f.name for f in dataclasses.fields(T)} else '--eval_freq=0')"
}

write_dataset() {  # (a) 4 episodes, 2 tasks, 6-d state, 3-d action, written by LeRobot's own API
  rm -rf "$WORK/lr_toy"
  "$PY" - "$WORK/lr_toy" <<'EOF'
import sys
import numpy as np
from lerobot.datasets.lerobot_dataset import LeRobotDataset

features = {"observation.state": {"dtype": "float32", "shape": (6,), "names": [f"s{i}" for i in range(6)]},
            "action": {"dtype": "float32", "shape": (3,), "names": ["dx", "dy", "grip"]}}
ds = LeRobotDataset.create("local/toy", fps=10, features=features, root=sys.argv[1], robot_type="toy", use_videos=False)
rng = np.random.default_rng(0)
for ep in range(4):
    task = ["push the block", "lift the cube"][ep % 2]
    goal = rng.normal(size=3).astype(np.float32)
    state = rng.normal(size=6).astype(np.float32)
    for t in range(40):
        action = np.tanh(goal - state[:3] + 0.5 * (ep % 2)).astype(np.float32)
        ds.add_frame({"observation.state": state.copy(), "action": action, "task": task})
        state[:3] += 0.1 * action
        state[3:] = np.sin(t / 10 + np.arange(3))
    ds.save_episode()
ds.finalize()
back = LeRobotDataset("local/toy", root=sys.argv[1])
assert back.num_episodes == 4 and back.num_frames == 160, (back.num_episodes, back.num_frames)
print("wrote", sys.argv[1], back.num_episodes, "episodes", back.num_frames, "frames")
EOF
}

train_on_dataset() {  # (b) exit 0, and the checkpoint keeps the dataset's task strings
  rm -rf "$WORK/ad_train"
  action-decoder train --dataset "$WORK/lr_toy" --steps 30 --batch-size 32 --output-dir "$WORK/ad_train" --seed 0 \
      || return 1
  "$PY" -c "import json, sys; t = json.load(open(sys.argv[1]))['extra']['tasks']; \
assert t == ['push the block', 'lift the cube'], t; print('tasks', t)" "$WORK/ad_train/final/config.json"
}

record_and_load() {  # (c) needs `action-decoder record` and Meta-World
  # grep without -q reads all of the help, so the writer never dies of SIGPIPE under pipefail.
  action-decoder --help 2>&1 | grep -w record > /dev/null \
    || { echo "action-decoder record: no such subcommand in this checkout"; return 1; }
  rm -rf "$WORK/rec"
  action-decoder record --task metaworld/reach --demos 2 --output-dir "$WORK/rec" --seed 0 || return 1
  "$PY" - "$WORK/rec" <<'EOF'
import sys
from lerobot.datasets.lerobot_dataset import LeRobotDataset

meta_ds = LeRobotDataset("local/rec", root=sys.argv[1])
fps = meta_ds.fps
ds = LeRobotDataset("local/rec", root=sys.argv[1], delta_timestamps={"action": [i / fps for i in range(16)]})
item = ds[len(ds) - 1]
assert ds.num_episodes == 2, ds.num_episodes
assert item["action"].shape[0] == 16 and bool(item["action_is_pad"][-1]), (item["action"].shape, item["action_is_pad"])
print("loaded", sys.argv[1], ds.num_episodes, "episodes", ds.num_frames, "frames, tasks", list(ds.meta.tasks.index))
EOF
}

lerobot_train() {  # (d)
  rm -rf "$WORK/lrt_$1"
  lerobot-train --policy.type=action_decoder --policy.decoder_type="$1" --policy.device=cpu \
      --policy.push_to_hub=false --dataset.repo_id=local/toy --dataset.root="$WORK/lr_toy" \
      --output_dir="$WORK/lrt_$1" --steps="$STEPS" --batch_size=16 --num_workers=0 --log_freq=10 \
      --save_freq="$STEPS" "$NO_EVAL" --wandb.enable=false
}

lerobot_train_ddp() {  # (d') LeRobot's accelerate path with 2 data-parallel processes (gloo on CPU)
  rm -rf "$WORK/lrt_ddp"
  torchrun --nproc_per_node 2 -m lerobot.scripts.lerobot_train --policy.type=action_decoder \
      --policy.decoder_type=mean_flow --policy.device=cpu --policy.push_to_hub=false --dataset.repo_id=local/toy \
      --dataset.root="$WORK/lr_toy" --output_dir="$WORK/lrt_ddp" --steps=10 --batch_size=8 --num_workers=0 \
      --log_freq=5 --save_freq=10 "$NO_EVAL" --wandb.enable=false || return 1
  grep -q "effective batch size: 16" "$WORK/logs/d_lerobot_train_ddp_mean_flow.log" || { echo "not data-parallel"; return 1; }
}

reload_and_act() {  # (e) LeRobot's from_pretrained + its saved processors + select_action
  "$PY" - "$WORK/lrt_$1/checkpoints/last/pretrained_model" "$WORK/lr_toy" <<'EOF'
import sys
import torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
from lerobot.utils.import_utils import register_third_party_plugins

register_third_party_plugins()          # what lerobot-train / lerobot-eval do: imports lerobot_policy_*
path, root = sys.argv[1:]
cfg = PreTrainedConfig.from_pretrained(path)
cfg.device = "cpu"
policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg)
pre, post = make_pre_post_processors(cfg, pretrained_path=path)
frame = LeRobotDataset("local/toy", root=root)[0]
policy.reset()
actions = [post(policy.select_action(pre({"observation.state": frame["observation.state"], "task": frame["task"]})))
           for _ in range(cfg.n_action_steps + 1)]
assert all(a.shape == (1, 3) and torch.isfinite(a).all() for a in actions), [a.shape for a in actions]
print(cfg.type, cfg.decoder_type, "tasks", cfg.tasks, "first action", actions[0].tolist())
EOF
}

success_of() {  # success rate in % from an action-decoder eval JSON or a lerobot-eval eval_info.json
  "$PY" -c "import json, sys; d = json.load(open(sys.argv[1])); \
print(round(d['overall']['pc_success'], 1) if 'overall' in d else round(100 * d['success_rate'], 1))" "$1"
}

state_policy_closed_loop() {  # (g) library state policy → convert → lerobot-eval vs action-decoder eval
  rm -rf "$WORK/mw_rec" "$WORK/mw_train" "$WORK/mw_lerobot" "$WORK/mw_eval" "$WORK/mw_ours.json"
  action-decoder record --task "metaworld/$MW_TASK" --demos "$MW_DEMOS" --layout lerobot --output-dir "$WORK/mw_rec" \
    && action-decoder train --dataset "$WORK/mw_rec" --steps "$MW_TRAIN_STEPS" --eval-episodes 0 \
         --output-dir "$WORK/mw_train" --seed 0 --no-progress \
    && action-decoder eval --checkpoint "$WORK/mw_train/final" --episodes "$MW_EPISODES" --output "$WORK/mw_ours.json" \
    && action-decoder convert --checkpoint "$WORK/mw_train/final" --to lerobot --output-dir "$WORK/mw_lerobot" \
    && lerobot-eval --policy.path="$WORK/mw_lerobot" --policy.device=cpu --env.type=metaworld \
         --env.task="$MW_TASK-v3" --eval.n_episodes="$MW_EPISODES" --eval.batch_size=1 --seed=0 \
         --output_dir="$WORK/mw_eval" || return 1
  local ours theirs
  ours=$(success_of "$WORK/mw_ours.json") && theirs=$(success_of "$WORK/mw_eval/eval_info.json") || return 1
  echo "$MW_TASK, $MW_EPISODES episodes: action-decoder eval $ours %, lerobot-eval $theirs %"
  "$PY" -c "import sys; a, b = map(float, sys.argv[1:]); sys.exit(0 if abs(a - b) <= 10 else 1)" "$ours" "$theirs" \
    || { echo "lerobot-eval $theirs % is more than 10 points from action-decoder eval $ours %"; return 1; }
}

camera_policy_closed_loop() {  # (h) record --layout lerobot --cameras corner2 → lerobot-train → lerobot-eval
  rm -rf "$WORK/cam_rec" "$WORK/cam_train" "$WORK/cam_eval"
  action-decoder record --task "metaworld/$MW_TASK" --demos "$CAM_DEMOS" --layout lerobot --cameras corner2 \
         --output-dir "$WORK/cam_rec" \
    && lerobot-train --policy.type=action_decoder --policy.device=cpu --policy.push_to_hub=false \
         --dataset.repo_id=local/cam --dataset.root="$WORK/cam_rec" --dataset.video_backend=pyav \
         --output_dir="$WORK/cam_train" --steps="$CAM_STEPS" --batch_size=16 --num_workers=0 --log_freq=50 \
         --save_freq="$CAM_STEPS" "$NO_EVAL" --wandb.enable=false \
    && lerobot-eval --policy.path="$WORK/cam_train/checkpoints/last/pretrained_model" --policy.device=cpu \
         --env.type=metaworld --env.task="$MW_TASK-v3" --eval.n_episodes="$CAM_EPISODES" --eval.batch_size=1 \
         --seed=0 --output_dir="$WORK/cam_eval" || return 1
  echo "camera policy ($CAM_DEMOS demos, $CAM_STEPS lerobot-train steps), $MW_TASK, $CAM_EPISODES episodes:" \
       "lerobot-eval $(success_of "$WORK/cam_eval/eval_info.json") %"
}

step venv setup_venv
if [ "$FAILED" = 0 ]; then
  NO_EVAL=$(no_env_eval)
  step a_write_dataset_lerobot_api write_dataset
  step b_action_decoder_train_dataset train_on_dataset
  step c_record_and_load_in_lerobot record_and_load
  for decoder in DDPM flow_matching mean_flow; do
    step "d_lerobot_train_$decoder" lerobot_train "$decoder"
    step "e_reload_select_action_$decoder" reload_and_act "$decoder"
  done
  step d_lerobot_train_ddp_mean_flow lerobot_train_ddp
  step f_plugin_tests_with_lerobot "$PY" -m pytest -q -p no:cacheprovider "$REPO/tests/test_lerobot_plugin.py"
  step i_serve_lerobot_robot_client "$PY" -m pytest -q -p no:cacheprovider "$REPO/tests/test_serve_lerobot.py"
  if [ -z "${LEROBOT_SKIP_CLOSED_LOOP:-}" ]; then
    step g_state_policy_lerobot_eval_metaworld state_policy_closed_loop
    step h_camera_policy_lerobot_eval_metaworld camera_policy_closed_loop
  fi
fi

echo "== LeRobot integration ($(cd "$REPO" && git rev-parse --short HEAD 2>/dev/null), work dir $WORK)"
printf '%s\n' "${SUMMARY[@]}"
for log in g_state_policy_lerobot_eval_metaworld h_camera_policy_lerobot_eval_metaworld; do
  [ -f "$WORK/logs/$log.log" ] && grep -h "lerobot-eval .* %" "$WORK/logs/$log.log" | tail -1
done
exit "$FAILED"
