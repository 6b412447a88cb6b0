# SPDX-License-Identifier: Apache-2.0
"""Build of the native EKF-likelihood kernel; everything else is in pyproject.toml."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "magcal.calib.likelihood._mekf",
            sources=["csrc/mekf_likelihood.c", "csrc/mekf_fisher.c", "csrc/_mekf_module.c"],
            include_dirs=["csrc"],
            # No auto-vectorisation: on the kernel's 3×3 arithmetic GCC 12 produces packed
            # code with shuffles that runs slower than scalar code (cost+gradient ~20%
            # faster without it, measured). Each operation is still one IEEE operation, so
            # the results do not change. That, and the bit-identical AVX clone of the hot
            # passes, also needs -ffp-contract=off: without it a compiler may fuse a*b + c
            # into one FMA with a single rounding (clang does so by default, GCC outside
            # ISO mode, whenever the target has FMA).
            extra_compile_args=[
                "-std=c99",
                "-O3",
                "-fno-tree-vectorize",
                "-fno-tree-slp-vectorize",
                "-ffp-contract=off",
                "-Wall",
                "-Wextra",
                "-Wpedantic",
            ],
        )
    ]
)
