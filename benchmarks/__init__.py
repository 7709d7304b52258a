"""`photopft bench`: figures measured on the simulated rig and reference data, printed and written to
docs/benchmarks.md. A source checkout's package, never shipped with the application; app/cli.py finds it
beside the checkout it runs from. Each bench is one module with `add(what)`, listed in BENCHES in the
order `photopft bench --help` shows them."""


BENCHES = ("accuracy", "speed", "integration", "motion", "record", "volume", "scales", "process", "population",
           "visible", "carry", "sides", "anchors", "live", "lights", "blows", "tidal", "compression", "gui")
