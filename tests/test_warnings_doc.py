"""docs/warnings.md lists every warning ilt can print, each with a test that makes ilt
print it, and every kind of error: a new warning or error class without a row fails here."""

import ast
import re

from tests import ROOT

DOC = (ROOT / "docs" / "warnings.md").read_text()


def table(title: str) -> list[list[str]]:
    section = DOC.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and not line.startswith("|---")]
    return [[cell.strip() for cell in row.strip("|").split(" | ")] for row in rows[1:]]


def literal(node) -> str:
    """A format string's text, each placeholder as '…'."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return re.sub(r"%[-+ #0-9.]*[sdfgre]", "…", node.value)
    if isinstance(node, ast.JoinedStr):
        return "".join(literal(v) if isinstance(v, ast.Constant) else "…" for v in node.values)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return literal(node.left) + literal(node.right)
    return "…"


def warning_sites() -> list[tuple[str, str]]:
    """(where, text) of every line ilt logs at WARNING or adds to a 'warnings' list."""
    sites = []
    for path in sorted((ROOT / "ilt").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.args):
                continue
            owner, name = ast.unparse(node.func.value), node.func.attr
            if owner == "log" and name == "warning":
                text = literal(node.args[0])
            elif owner == "log" and name == "log" and "WARNING" in ast.unparse(node.args[0]):
                text = literal(node.args[1])
            elif owner == "warnings" and name == "append":
                text = literal(node.args[0])
            else:
                continue
            if re.search(r"[a-z]{3}", text):     # not a line that forwards another's text ('%s: %s')
                sites.append((f"{path.relative_to(ROOT)}:{node.lineno}", text))
    return sites


def test_every_warning_ilt_can_print_has_a_row():
    fragments = [row[0].strip("`") for row in table("Warnings")]
    missing = [(where, text) for where, text in warning_sites() if not any(f in text for f in fragments)]
    assert not missing, f"warnings without a row in docs/warnings.md: {missing}"
    assert len(warning_sites()) >= 20


def test_each_row_is_reached_by_a_test_that_asserts_it():
    faults = []
    for row in table("Warnings"):
        fragment, test = row[0].strip("`"), row[-1].strip("`")
        path, name = test.split("::")
        source = (ROOT / path).read_text()
        match = re.search(rf"^def {name}\(.*?(?=^def |^@|\Z)", source, flags=re.DOTALL | re.MULTILINE)
        if not match:
            faults.append(f"{test}: no such test (row {fragment!r})")
        elif fragment not in match.group(0).replace("\\'", "'"):
            faults.append(f"{test} does not assert {fragment!r}")
    assert not faults


def test_every_error_class_is_listed():
    listed = {name for row in table("Errors") for name in re.findall(r"`(\w+)`", row[0])}
    classes = set()
    for path in (ROOT / "ilt").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    re.search(r"Error|Exception|Lambertian|Memory|Input|Lost", ast.unparse(b)) for b in node.bases):
                classes.add(node.name)
    classes.discard("IltError")     # the command line's carrier of every error's one line
    assert not classes - listed, f"error classes without a row in docs/warnings.md: {sorted(classes - listed)}"
