"""The package's compiled part: kNN refinement's vote on the CPU (rangeret/inference/csrc). The
rest of the build is in pyproject.toml. `optional`: where no C compiler is found the package
still installs, and the CPU runs the vote in torch (see rangeret/inference/knn_native.py)."""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "rangeret.inference._knn_vote",
            sources=["rangeret/inference/csrc/knn_vote.c"],
            depends=["rangeret/inference/csrc/knn_vote_body.h"],
            # no fused multiply-add: every distance is rounded as the published code rounds it
            extra_compile_args=["-O3", "-ffp-contract=off", "-Wno-psabi"],
            optional=True,
        )
    ]
)
