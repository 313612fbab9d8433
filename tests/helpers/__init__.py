"""Shared helpers of the test suite, one home each (tests/conftest.py holds only the root fixtures).

- :mod:`helpers.devices`: the devices the tests run on (``DEVICES``, ``CUDA_OK``, ``requires_cuda``);
- :mod:`helpers.dtypes`: the float dtypes and their tolerances;
- :mod:`helpers.clouds`: the LiDAR-like cloud generator (``lidar_cloud``, on lidarops.data.clouds) and the
  other synthetic clouds of the op tests;
- :mod:`helpers.compare`: exact and tolerant comparisons that say where tensors differ;
- :mod:`helpers.boxes`, :mod:`helpers.kitti`, :mod:`helpers.sparse`, :mod:`helpers.voxelize`,
  :mod:`helpers.compat`, :mod:`helpers.pillars`, :mod:`helpers.models`: data and references of one area each.

``tests/`` is not a package (its folders are): pytest puts it on ``sys.path``, so ``helpers`` imports as a
top-level package, from test files and from ``benchmarks/`` (which add ``tests/`` to ``sys.path``).
"""
