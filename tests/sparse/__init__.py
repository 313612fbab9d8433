"""Tests of lidarops/sparse/ (sparse convolution, fused layers, indice keys, the nn modules)."""
