"""Warp kernels of the warpsense camera (installed as ``warpsense.kernels``; no torch import here).

Each module defines a forward kernel and an explicit backward kernel, generic over the float type, with float32
and float64 overloads registered at import. Modules compile with ``enable_backward=False``: the adjoints are written
by hand, which compiles faster and keeps reductions deterministic.
"""
