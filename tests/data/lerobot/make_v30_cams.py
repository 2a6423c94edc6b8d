"""Write `v30_cams/` with LeRobot's own API (run with a Python that has lerobot==0.4.4 installed):

    python tests/data/lerobot/make_v30_cams.py tests/data/lerobot/v30_cams

Three episodes (12, 9 and 14 frames), fps 10, two video cameras of 32×32 encoded by LeRobot's
default codec (AV1, libsvtav1, crf 30). Every frame says which episode and frame it is, so a
reader's alignment can be checked from the pixels alone (`frame_image` is the generator the tests
share): the grey level of the background encodes the frame (top: 10 + 12·frame, wrist:
180 − 12·frame) and an 8×8 near-white square in row 1 of a 4×4 grid of cells the episode (column
= episode; the wrist camera mirrors it). A square that jumps from cell to cell with the frame does
not survive LeRobot's AV1 settings at this size (some P-frames keep the previous position), a
background level does (within 2 levels).
``observation.state`` is ``[episode, frame, 0, 0]``, ``action`` ``[frame / 10, -episode]``.
"""

import sys

import numpy as np

LENGTHS = (12, 9, 14)
CAMERAS = ("observation.images.top", "observation.images.wrist")
SIZE, CELL, FPS = 32, 8, 10


def frame_image(camera: str, episode: int, frame: int) -> np.ndarray:
    """[32, 32, 3] uint8 of ``camera`` at ``frame`` of ``episode``."""
    wrist = camera.endswith("wrist")
    image = np.full((SIZE, SIZE, 3), (180 - 12 * frame) if wrist else (10 + 12 * frame), np.uint8)
    col = SIZE // CELL - 1 - episode if wrist else episode
    image[CELL:2 * CELL, col * CELL:(col + 1) * CELL] = 250
    return image


def main(root: str) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    video = {"dtype": "video", "shape": (SIZE, SIZE, 3), "names": ["height", "width", "channels"]}
    features = {"observation.state": {"dtype": "float32", "shape": (4,), "names": ["episode", "frame", "z0", "z1"]},
                "action": {"dtype": "float32", "shape": (2,), "names": ["a0", "a1"]},
                **{camera: dict(video) for camera in CAMERAS}}
    ds = LeRobotDataset.create("local/v30_cams", FPS, features, root=root, robot_type="toy", use_videos=True)
    for episode, length in enumerate(LENGTHS):
        for frame in range(length):
            ds.add_frame({"observation.state": np.array([episode, frame, 0, 0], np.float32),
                          "action": np.array([frame / 10, -episode], np.float32),
                          **{camera: frame_image(camera, episode, frame) for camera in CAMERAS},
                          "task": "look at the square"})
        ds.save_episode()
    ds.finalize()


if __name__ == "__main__":
    main(sys.argv[1])
