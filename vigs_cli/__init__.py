"""The ``vigs`` command line: thin argument parsing that calls ``vigs_core`` (and ``vigs_ros``)."""
