"""Files: atomic writes (atomic.py) and Gaussians as PLY in the 3DGS layout (ply.py)."""
from .atomic import (atomic_path, atomic_save_npz, atomic_save_png, atomic_write_bytes,
                     atomic_write_json, atomic_write_text, to_uint8)
from .ply import gaussian_ply_properties, read_gaussians_ply, write_gaussians_ply

__all__ = ["atomic_path", "atomic_save_npz", "atomic_save_png", "atomic_write_bytes",
           "atomic_write_json", "atomic_write_text", "to_uint8", "gaussian_ply_properties",
           "read_gaussians_ply", "write_gaussians_ply"]
