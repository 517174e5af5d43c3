#!/usr/bin/env bash
# The suite on other floating-point kernels than this machine picks: OpenCV, NumPy and OpenBLAS held to AVX2 (no
# AVX-512), as on a machine of another kind. The last bits of every figure change (the project's Intel Xeon and AMD
# EPYC machines differ so), so a bound that passes here and under make test holds by a margin, not by luck of
# the bits. Usage: make test-bits [ARGS="-k pattern"]
set -euo pipefail
cd "$(dirname "$0")/.."
export OPENCV_CPU_DISABLE=AVX512-SKX
export NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR"
export OPENBLAS_CORETYPE=Haswell
.venv/bin/python -c "import cv2, numpy; print('kernels:', cv2.getCPUFeaturesLine(), '| numpy', numpy.__config__.CONFIG['SIMD Extensions'].get('found'))" || true
.venv/bin/python -m pytest -q -p no:cacheprovider "$@"
