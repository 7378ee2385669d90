"""Generated reference pages are in sync with the code they describe."""
import os

from clppm.cli.reference import reference_markdown

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


def test_cli_reference_is_generated_from_the_parsers():
    """docs/cli.md is `python -m clppm.cli.reference > docs/cli.md`: regenerate after changing an
    option."""
    with open(os.path.join(ROOT, "docs", "cli.md"), encoding="utf-8") as f:
        assert f.read() == reference_markdown()
