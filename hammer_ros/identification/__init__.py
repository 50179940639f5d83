"""The papers' identification methods and the pieces they share (pure numpy/scipy, no ROS).

One module per paper method: ``correlation_least_squares`` (paper 000: CLS, Bai's NLS, plain LS),
``era`` (the eigensystem realisation behind mu-Markov), ``piecewise_linear_ls`` (paper 001: PLLS),
``semiparametric`` (paper 002), ``billings_fakhouri`` (paper 003). Shared pieces: ``linear``
(transfer functions), ``static_maps`` (the nonlinearities), ``regression`` (regressor builders and
least squares), ``correlation``, ``simulate``, ``excitation`` (test signals), ``result`` (the
identified model and its JSON) and ``methods`` (the ``--method`` table and ``identify``).
May import: numpy, scipy, ``hammer_ros.errors``. Never rclpy, never another layer.
"""
