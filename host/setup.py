"""Build of the native EKF-likelihood kernel; everything else is in pyproject.toml."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "magcal.calib._mekf",
            sources=["csrc/mekf_likelihood.c", "csrc/_mekf_module.c"],
            include_dirs=["csrc"],
            extra_compile_args=["-std=c99", "-O3", "-Wall", "-Wextra"],
        )
    ]
)
