"""The Map-free dataset on disk: lazy scenes and frames, readers and writers, overlaps, the download check."""

from .check import CheckReport, check_dataset, check_scene
from .device import DevicePoses, DriftModel, load_device_poses, multiframe_bursts, scene_bursts
from .io import (
    FormatError,
    PoseTable,
    check_depth_size,
    depth_path_for,
    read_depth,
    read_image,
    read_intrinsics,
    read_poses,
    write_depth,
    write_intrinsics,
    write_poses,
)
from .overlaps import Overlaps, read_overlaps, write_overlaps
from .scene import REFERENCE_NAME, SPLITS, Dataset, Frame, Scene, frame_number, scored_query_names

__all__ = [
    "FormatError",
    "PoseTable",
    "check_depth_size",
    "depth_path_for",
    "read_depth",
    "read_image",
    "read_intrinsics",
    "read_poses",
    "write_depth",
    "write_intrinsics",
    "write_poses",
    "Overlaps",
    "read_overlaps",
    "write_overlaps",
    "REFERENCE_NAME",
    "SPLITS",
    "Dataset",
    "Frame",
    "Scene",
    "frame_number",
    "scored_query_names",
    "DevicePoses",
    "DriftModel",
    "load_device_poses",
    "multiframe_bursts",
    "scene_bursts",
    "CheckReport",
    "check_dataset",
    "check_scene",
]
