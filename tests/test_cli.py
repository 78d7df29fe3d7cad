from typer.testing import CliRunner

from cli import app

runner = CliRunner()


def test_help_lists_every_command():
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    for cmd in (
        "demo",
        "simulate",
        "convert",
        "info",
        "run",
        "evaluate",
        "export",
        "experiment",
        "diff",
        "view",
        "bench",
    ):
        assert cmd in res.output
