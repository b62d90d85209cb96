"""Embedded data of synthbos: density snapshots and regression baselines (package data).

Read them with :func:`synthbos.data_file`; this module holds no code.
"""
