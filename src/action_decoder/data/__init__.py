"""Demonstrations, LeRobot-layout datasets, chunked training samples and normalisation statistics."""

from .chunks import ChunkDataset
from .demos import cache_root, generate_demos, load_demos, record_demos
from .episodes import ACTION, CONTINUATION, PREFIX_LENGTH, STATE, EpisodeDataset, concat_datasets
from .lerobot_format import load_dataset
from .lerobot_write import write_episodes
from .perturbed_prefixes import PerturbedPrefixes, perturbed_labels
from .relabel import relabel_episodes
from .stats import ACTION_CONSTANT_BELOW, STD_FLOOR, compute_stats, load_stats, save_stats

__all__ = [
    "ACTION",
    "CONTINUATION",
    "PREFIX_LENGTH",
    "STATE",
    "ACTION_CONSTANT_BELOW",
    "STD_FLOOR",
    "ChunkDataset",
    "EpisodeDataset",
    "PerturbedPrefixes",
    "cache_root",
    "compute_stats",
    "concat_datasets",
    "generate_demos",
    "load_dataset",
    "load_demos",
    "load_stats",
    "perturbed_labels",
    "record_demos",
    "relabel_episodes",
    "save_stats",
    "write_episodes",
]
