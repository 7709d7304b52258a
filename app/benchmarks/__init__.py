"""`photopft bench`: the benchmarks. Not shipped in the installed application (pyproject.toml
leaves this package out of the wheel, the bundle leaves it out too); they run from a source checkout."""
