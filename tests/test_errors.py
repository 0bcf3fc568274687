"""The one exception tree (stage/errors.py): every error lives there and says what it means."""

from __future__ import annotations

import ast
from pathlib import Path

import stage.errors as errors

ROOT = Path(__file__).resolve().parents[1]


def _errors() -> list[type]:
    return [obj for obj in vars(errors).values()
            if isinstance(obj, type) and issubclass(obj, errors.StageError)]


def test_every_error_says_in_one_line_what_it_means_and_how_stage_exits():
    assert {cls.__name__ for cls in _errors()} == set(errors.__all__)
    for cls in _errors():
        doc = cls.__doc__ or ""
        assert doc.strip() and "\n" not in doc.strip(), cls
        # the CLI exits 2 for BadInput, 1 for any other StageError (stage.cli.main.main)
        assert ("exit 2" if issubclass(cls, errors.BadInput) else "exit 1") in doc, cls


def test_bad_input_and_run_time_failures_are_told_apart_by_class():
    bad = {cls.__name__ for cls in _errors() if issubclass(cls, errors.BadInput)}
    assert bad == {"BadInput", "ConfigError", "RecordingError", "MusicError"}
    assert not issubclass(errors.TransportError, errors.BadInput)
    assert not issubclass(errors.CalibrationError, errors.BadInput)


def test_no_other_module_defines_a_public_exception():
    """Private control-flow exceptions (``_Drop``, ``_Disabled``) may stay in their module."""
    elsewhere = []
    for path in [*(ROOT / "stage").rglob("*.py"), *(ROOT / "plugins").rglob("*.py")]:
        if path == ROOT / "stage" / "errors.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                bases = [ast.unparse(b).rsplit(".", 1)[-1] for b in node.bases]
                if any(b.endswith(("Error", "Exception")) for b in bases):
                    elsewhere.append(f"{path.relative_to(ROOT)}: {node.name}")
    assert elsewhere == []
