"""Scenes: COLMAP loading, the sparse-view split, train-view triangulation, initialisation and
the self-made demo scene (clauses DAT-01..DAT-15, docs/spec/data.md)."""
from .colmap import MAX_DISTORTION_PX, Scene, load_scene
from .demo import demo_scene_path, make_demo_scene
from .init import init_gaussians_from_points, knn_log_scales
from .pointcloud import read_ply, write_ply
from .split import LLFF_HOLD, split_views
from .triangulate import TRIANGULATION_PRESETS, triangulate_train_views

__all__ = [
    "Scene", "load_scene", "MAX_DISTORTION_PX",
    "split_views", "LLFF_HOLD",
    "triangulate_train_views", "TRIANGULATION_PRESETS",
    "read_ply", "write_ply",
    "init_gaussians_from_points", "knn_log_scales",
    "make_demo_scene", "demo_scene_path",
]
