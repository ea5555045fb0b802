"""``relaxmap run``: the process graph (data in ``deploy/``), its supervisor, and the run's outputs."""
