"""Every Warp kernel module compiles for a GPU on a machine without one: Warp's CUDA code generation and NVRTC
(bundled with Warp) turn each module, with its float32 and float64 overloads, into sm_90 (H100) PTX. A kernel
that runs on the CPU backend can still fail to build for CUDA; this catches it in CI, where no GPU is present."""

import importlib
import pkgutil

import pytest
import warp as wp

import warpsense.kernels
import warpsense.ops  # noqa: F401  - the ops import their kernel modules, which register the overloads

MODULES = sorted(info.name for info in pkgutil.iter_modules(warpsense.kernels.__path__))


def test_every_kernel_module_is_listed():
    assert {"cfa", "cross_entropy", "lovasz", "noise", "psf", "quantize", "sensor", "smoothness"} <= set(MODULES)


@pytest.mark.parametrize("name", MODULES)
def test_kernel_module_compiles_for_cuda(name, tmp_path):
    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp build has no NVRTC for sm_90")
    module = importlib.import_module(f"warpsense.kernels.{name}")
    wp.compile_aot_module(module, arch=90, module_dir=tmp_path, use_ptx=True)
    assert list(tmp_path.glob("*.sm90.ptx")), f"no PTX written for warpsense.kernels.{name}"


def test_psf_kernels_of_the_recipes_size_compile_for_cuda(tmp_path):
    """The PSF forward and image adjoint are built per kernel size, each in a module of its own: K = 15's."""
    if 90 not in wp.get_cuda_supported_archs():
        pytest.skip("this Warp build has no NVRTC for sm_90")
    from warpsense.kernels.psf import psf_kernels

    for index, kernel in enumerate(psf_kernels(15)):
        wp.compile_aot_module(kernel.module, arch=90, module_dir=tmp_path / str(index), use_ptx=True)
        assert list((tmp_path / str(index)).glob("*.sm90.ptx")), f"no PTX written for {kernel.key}"
