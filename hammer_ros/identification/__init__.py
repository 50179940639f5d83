"""The papers' identification methods and the pieces they share (pure numpy/scipy, no ROS).

One module per paper method: ``correlation_least_squares`` (paper 000: CLS, Bai's NLS, plain LS),
``era`` (the eigensystem realisation behind mu-Markov), ``piecewise_linear_ls`` (paper 001: PLLS),
``semiparametric`` (paper 002), ``billings_fakhouri`` (paper 003). Shared pieces: ``linear``
(transfer functions), ``static_maps`` (the nonlinearities), ``regression`` (regressor builders and
least squares), ``correlation``, ``simulate`` (with ``compiled_loops``: numba kernels of the
sample-by-sample loops), ``cls_kernel`` (the compiled CLS solve, with ``cls_bounds_kernel`` and
``cls_numerics``), ``simulation_error`` and ``refinement`` (any estimate refined on the
simulation error, ``identify --refine``; ``levenberg_marquardt`` with ``levenberg_marquardt_kernel``,
MINPACK's lmder, their optimiser), ``excitation`` (test signals), ``result`` (the
identified model and its JSON) and ``methods`` (the ``--method`` table and ``identify``).
May import: numpy, scipy, numba (compiled loops, with a pure-numpy fallback), ``hammer_ros.errors``.
Never rclpy, never another layer.
"""

__all__ = [
    "affine", "billings_fakhouri", "closed_loop", "cls_bounds_kernel", "cls_kernel", "cls_numerics",
    "compiled_loops", "correlation", "correlation_least_squares", "era", "excitation", "instrumental",
    "levenberg_marquardt", "levenberg_marquardt_kernel", "linear", "methods", "piecewise_linear_ls", "refinement",
    "regression", "result", "runs", "semiparametric", "simulate", "simulation_error", "static_maps", "trust",
    "uncertainty",
]
