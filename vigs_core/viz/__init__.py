"""Visualisation of runs: live 3D view and recordings with rerun (:mod:`vigs_core.viz.rerun_log`)."""
