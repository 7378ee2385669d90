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


# ----------------------------------------------------------------------------- measured figures
# Every image of README.md and docs/*.md, and every table of measured figures there, is made by
# bench/report.py: it stands inside a report block (between `<!-- report:NAME -->` and
# `<!-- /report:NAME -->`) whose last line is the stamp "*Made by `python bench/report.py --only
# JOB ...` on CPU with IMPLEMENTATION ..., clppm COMMIT, DATE.*", and each PNG carries the same
# stamp in its text metadata (key "Stamp").
#
# The rule for tables: a table outside a report block is a measured table when a cell of its body
# (not the header row) holds a measured-looking number outside backticks (code spans hold
# options, keys and literal constants): a number with a decimal fraction, a number in scientific
# form (1e5, 1.2·10⁶), or a number followed by a unit of time, share, size, rate or ratio (%, s,
# ms, min, B, KB, MB, MiB, GB, GiB, /s, ×, x). Lengths and wavelengths are left out: they describe
# scenes (10 mm of forearm, 5 nm bands), not measurements. Reference tables (options, config keys, exit codes, file lists) hold
# none. Pages that are generated or owned elsewhere are exempt as a whole: GENERATED.
import re
import struct
import zlib

GENERATED = {"api.md", "cli.md", "config.md", "architecture.md"}
BLOCK = re.compile(r"<!-- report:([\w-]+) -->\n(.*?)<!-- /report:\1 -->", re.S)
STAMP = re.compile(r"^\*Made by `python bench/report\.py --only [\w,-]+[^`]*`(?: \(quick[^)]*\))? on .+ with .+, "
                   r"clppm [0-9a-f]{7,}(\+dirty)?, \d{4}-\d\d-\d\d\.\*$", re.M)
IMAGE = re.compile(r"!\[[^\]]*\]\(([^)\s]+)\)|<img [^>]*src=\"([^\"]+)\"")
CODE = re.compile(r"`[^`]*`")
MEASURED = re.compile(r"(?<![\w.])(\d+\.\d+|\d+(\.\d+)?(e[+-]?\d+|·10))(?![\w.])"
                      r"|\d\s?(%|s|ms|min|B|KB|MB|MiB|GB|GiB|/s)(?![\w])"
                      r"|\d\s?[×x](?![\w\d])")


def pages() -> list[str]:
    docs = os.path.join(ROOT, "docs")
    return [os.path.join(ROOT, "README.md")] + sorted(
        os.path.join(docs, p) for p in os.listdir(docs) if p.endswith(".md") and p not in GENERATED)


def read(page: str) -> str:
    with open(page, encoding="utf-8") as f:
        return f.read()


def outside_blocks(text: str) -> str:
    return BLOCK.sub("", text)


def tables(text: str) -> list[list[str]]:
    """Each Markdown table's lines (header, separator, body)."""
    out, cur = [], []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            cur.append(line)
        elif cur:
            out.append(cur)
            cur = []
    return out


def is_measured(table: list[str]) -> bool:
    body = table[2:] if len(table) > 1 and set(table[1]) <= set("|-: ") else table
    return any(MEASURED.search(CODE.sub("", line)) for line in body)


def png_text(path: str) -> dict:
    """A PNG's tEXt, iTXt and zTXt chunks."""
    with open(path, "rb") as f:
        data = f.read()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    out, i = {}, 8
    while i < len(data):
        n, kind = struct.unpack(">I4s", data[i:i + 8])
        body = data[i + 8:i + 8 + n]
        i += 12 + n
        if kind == b"tEXt":
            k, v = body.split(b"\0", 1)
            out[k.decode("latin-1")] = v.decode("latin-1")
        elif kind == b"zTXt":
            k, v = body.split(b"\0", 1)
            out[k.decode("latin-1")] = zlib.decompress(v[1:]).decode("latin-1")
        elif kind == b"iTXt":
            k, rest = body.split(b"\0", 1)
            comp, rest = rest[0], rest[2:]
            _lang, rest = rest.split(b"\0", 1)
            _tkey, v = rest.split(b"\0", 1)
            out[k.decode("latin-1")] = (zlib.decompress(v) if comp else v).decode("utf-8")
    return out


def test_every_report_block_has_a_stamp():
    for page in pages():
        for name, body in BLOCK.findall(read(page)):
            assert body.strip(), f"{os.path.basename(page)}: report block {name} is empty: run bench/report.py"
            assert STAMP.search(body), f"{os.path.basename(page)}: report block {name} has no stamp line"


def test_every_image_is_made_by_the_report_and_stamped():
    for page in pages():
        text = read(page)
        for m in IMAGE.finditer(outside_blocks(text)):
            raise AssertionError(f"{os.path.basename(page)}: image {m.group(1) or m.group(2)} is outside a "
                                 "report block (bench/report.py makes every image)")
        for _name, body in BLOCK.findall(text):
            for m in IMAGE.finditer(body):
                path = os.path.normpath(os.path.join(os.path.dirname(page), m.group(1) or m.group(2)))
                assert os.path.isfile(path), f"{os.path.basename(page)}: {path} is missing"
                stamp = png_text(path).get("Stamp", "")
                assert "python bench/report.py --only" in stamp, f"{path} carries no report stamp"


def test_every_measured_table_is_a_report_block():
    for page in pages():
        for t in tables(outside_blocks(read(page))):
            assert not is_measured(t), (f"{os.path.basename(page)}: a table of measured figures outside a "
                                        f"report block: {t[0][:80]}")


def test_the_measured_table_rule():
    """The rule's edges: units, fractions and scientific numbers count; code spans and counts do not."""
    def measured(row):
        return is_measured(["| a | b |", "|---|---|", row])
    assert measured("| x | 3.44 % |") and measured("| x | 97 s |") and measured("| x | 1.1·10⁷ |")
    assert measured("| x | 4.5e5 |") and measured("| x | 7.7× |") and measured("| x | 22144 B |")
    assert not measured("| `clppm render --passes 7` | the default |")
    assert not measured("| 130 / 143 | stopped by SIGINT / SIGTERM |")
    assert not measured("| forearm | 320×240, `Rd 0.09739` |")
