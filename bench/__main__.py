from bench.cli import HARNESS, app

app(prog_name=HARNESS)
