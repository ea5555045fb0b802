"""relaxmap services: one package per service, a pure core and a thin bus node each."""
