"""Warp kernels of s3o-warp, exposed as differentiable torch ops (installed as ``s3o_warp.kernels``).

Shape glossary used by every docstring:
    T frames, V (or N) vertices, F faces, B bones, J joints, E edges, H x W image rows x columns.

Conventions: OpenCV camera (+x right, +y down, +z forward); intrinsics K are 3x3, one for all frames
``(3, 3)`` or one per frame ``(T, 3, 3)``; the centre of pixel (column c, row r) is at (c, r), so an
image spans [-0.5, W - 0.5] x [-0.5, H - 0.5]. Tensors are float32 on ``cpu`` or ``cuda``; the device
follows the inputs. Each op has a dense pure-torch twin ``<op>_reference`` in
``s3o_warp.reference`` (same signature) that defines the right answer.
"""
