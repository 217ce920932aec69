"""torchrot's Triton kernels (CUDA, ROCm and XPU; CPU tensors under Triton's
interpreter): the algorithm of csrc/kernel/ written once more, file for file
and name for name, as Triton functions on lanes.
"""
