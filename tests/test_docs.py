"""Generated reference pages are in sync with the code they describe."""
import os

from clppm.cli.reference import reference_markdown

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def test_cli_reference_is_generated_from_the_parsers():
    """docs/cli.md is `python -m clppm.cli.reference > docs/cli.md`: regenerate after changing an
    option."""
    with open(os.path.join(ROOT, "docs", "cli.md"), encoding="utf-8") as f:
        assert f.read() == reference_markdown()


def test_api_reference_is_generated_from_the_docstrings():
    """docs/api.md is `python -m clppm.apiref > docs/api.md`: regenerate after changing a public
    function's docstring or signature."""
    from clppm.apiref import reference_markdown as api_markdown
    with open(os.path.join(ROOT, "docs", "api.md"), encoding="utf-8") as f:
        assert f.read() == api_markdown()


def test_public_api_has_docstrings():
    """What help() shows for every public function and the render's result."""
    from clppm.apiref import PUBLIC
    import importlib
    for module, names in PUBLIC:
        for name in names:
            doc = getattr(importlib.import_module(module), name).__doc__ or ""
            assert len(doc.split()) >= 8, f"{module}.{name} has no docstring to speak of"
