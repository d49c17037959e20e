"""Backends for the oracle besides refgs itself.

    torch_backend   an independent PyTorch autograd transcription of the forward model
                    (``oracle.adapters.torch_backend:torch_float64`` etc.; needs torch)
    gsplat_backend  gsplat 1.5.3's pure-torch stage functions, and gsplat.rasterization where CUDA
                    is available (``oracle.adapters.gsplat_backend:gsplat_backend``; needs gsplat)

Modules are imported on demand: importing this package needs neither torch nor gsplat.
"""
