"""Fleet replay: many bags through ``replay`` on Dask distributed, and what changed.

``sources`` (bags, manifests, labels, groups), ``tasks`` (the per-bag task: ``io.replay`` as
``hammer-ros replay`` runs it, plus ``diagnose``), ``runner`` (the Dask client, progress,
checkpoints, resume, Ctrl-C), ``table`` (model quantities, ``fleet.parquet``), ``changes`` (the
robust change test, pure numpy), ``report`` (``fleet.html``), ``sample_fleet`` (the generator).
May import: numpy, pyarrow, dask/distributed (``runner`` only, when it runs), matplotlib
(``report``), ``hammer_ros.io``, ``messages``, ``streaming``, ``identification``, ``diagnosis``,
``errors``. Never rclpy, ``ros``, ``reproduce``, ``cli`` or ``tools``.
"""

__all__ = ["changes", "report", "runner", "sample_fleet", "sources", "table", "tasks"]
