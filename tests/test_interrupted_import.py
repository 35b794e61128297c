"""A signal that arrives while a library a stage imports late is initialising (Open3D in the feed-forward fusion)
comes out of the C extension as an ImportError ("initialization failed"); the command reads it as the interruption
it is: one line and the interrupted exit code, no traceback. An ImportError with no signal behind it is not hidden."""

import pytest

import ffrecon.cli as cli
from ffrecon.cli import signals
from ffrecon.errors import Interrupted


def _failing_import(received: bool):
    def command(args):
        if received:
            signals.received.append(15)
        raise ImportError("initialization failed")

    return command


def test_an_import_broken_by_a_signal_is_an_interruption(monkeypatch, capsys):
    monkeypatch.setattr(signals, "received", [])
    monkeypatch.setattr(cli, "_command", _failing_import(received=True))
    assert cli.main(["inspect-model", "x.onnx"]) == Interrupted.exit_code
    err = capsys.readouterr().err
    assert err.strip() == "ffrecon: interrupted; earlier results are untouched"


def test_an_import_error_without_a_signal_is_not_hidden(monkeypatch):
    monkeypatch.setattr(signals, "received", [])
    monkeypatch.setattr(cli, "_command", _failing_import(received=False))
    with pytest.raises(ImportError):
        cli.main(["inspect-model", "x.onnx"])
