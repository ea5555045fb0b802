"""Map relaxation: compass-mode relaxation and exact solve, pose-graph optimisation, map file formats."""
