"""Traversals on NVIDIA GPUs through numba-cuda: the CPU's per-ray bodies, compiled for CUDA.

``accel.intersect(..., device="cuda")`` and ``occluded`` run the traversals listed in
:data:`rayaccel.cuda.device.CUDA_TRAVERSALS` on the GPU. :mod:`~rayaccel.cuda.retarget`
compiles each traversal's CPU per-ray body for CUDA (one source, two targets);
:mod:`~rayaccel.cuda.skeleton` runs it in persistent warps (Aila & Laine 2009);
:mod:`~rayaccel.cuda.device` keeps layouts on the device and takes rays from numpy or
any ``__cuda_array_interface__`` array; :mod:`~rayaccel.cuda.report` compiles PTX without
a GPU and reads registers and occupancy with one. Importing this package does not
import ``numba.cuda``; its modules do.
"""
