"""Build of memlog's one compiled kernel (the rest is pyproject.toml).

``memlog/scoring/_entropy.c`` is plain C, loaded with ctypes by ``memlog.scoring.entropy``. It is
optional: without a C compiler the install goes on and memlog computes the same entropy maps with
numpy, about three times slower (``memlog models`` and the scoring log say which one runs).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("memlog.scoring._entropy", sources=["memlog/scoring/_entropy.c"], optional=True,
                  extra_compile_args=["-O3"] if not __import__("sys").platform.startswith("win") else []),
    ],
)
