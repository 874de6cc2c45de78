"""Console entry points: thin argument parsing around the library (see pyproject [project.scripts])."""
