"""Translation checks, for the tests (tests/unit/test_translations.py) and for whoever marks text.

    python -m tests.translations unmarked [FILE...]      template text not marked for translation
    python -m tests.translations extract FILE...          the catalogue (PO) of what FILE... mark
    python -m tests.translations missing                  marked strings without a German text
    python -m tests.translations compile [FILE...]        templates that do not compile (syntax)
    python -m tests.translations update                   `make translations`: catalogues up to date, compiled

A template's text is "marked" when it is inside {% translate %} or {% blocktranslate %}; what
is left outside (text between tags, and the human attributes: title, aria-label, placeholder,
alt, data-label, data-confirm*) must hold no words. Words that are the same in every language
(ROS state and transition names, units, product names) are allowed (SAME_IN_EVERY_LANGUAGE).
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tempfile
from html.parser import HTMLParser
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TEMPLATES = ROOT / "templates"
LOCALE = ROOT / "locale"
LANGUAGES = ("de",)
HUMAN_ATTRIBUTES = re.compile(r"^(title|aria-label|aria-description|placeholder|alt|data-label|data-confirm.*)$")
# The same in German: ROS names (states, transitions, topics), units, formats, product names.
SAME_IN_EVERY_LANGUAGE = {
    "unconfigured", "inactive", "active", "finalized", "configure", "activate", "deactivate", "cleanup",
    "shutdown", "configuring", "activating", "deactivating", "cleaningup", "shuttingdown", "errorprocessing",
    "ros", "dds", "rclpy", "rosout", "json", "yaml", "csv", "api", "utc", "url", "id", "cpu", "pid", "ok",
    "ms", "s", "min", "h", "hz", "kb", "mb", "gb", "kib", "mib", "gib", "redis", "oidc", "ldap",
    "debug", "info", "warn", "warning", "error", "fatal", "http", "https", "ssh", "tls",  # ROS log levels as shown
}
PLACEHOLDER = "\uE000"  # stands for a template tag or variable in the rebuilt text
WORD = re.compile(r"[^\W\d_]{2,}", re.UNICODE)


def _words(text: str) -> list[str]:
    text = text.replace(PLACEHOLDER, " ")
    return [w for w in WORD.findall(text) if w.lower() not in SAME_IN_EVERY_LANGUAGE]


def _rebuilt(source: str) -> str:
    """The template with marked text, tags, variables and comments replaced by PLACEHOLDER."""
    from django.template.base import Lexer, TokenType

    out: list[str] = []
    skipping: list[str] = []  # the end tag awaited: endblocktranslate, endcomment, endverbatim
    for token in Lexer(source).tokenize():
        if token.token_type == TokenType.BLOCK:
            name = token.contents.split()[0] if token.contents else ""
            if skipping:
                if name == skipping[-1]:
                    skipping.pop()
                out.append(PLACEHOLDER)
                continue
            if name in ("blocktranslate", "blocktrans"):
                skipping.append("end" + name)
            elif name == "comment":
                skipping.append("endcomment")
            out.append(PLACEHOLDER)
        elif token.token_type == TokenType.TEXT and not skipping:
            out.append(token.contents)
        else:
            out.append(PLACEHOLDER if token.token_type != TokenType.COMMENT else "")
    return "".join(out)


class _Texts(HTMLParser):
    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.found: list[str] = []
        self._raw = 0  # inside <script> or <style>

    def handle_starttag(self, tag, attrs):
        if tag in ("script", "style"):
            self._raw += 1
        for name, value in attrs:
            if value and HUMAN_ATTRIBUTES.match(name) and _words(value):
                self.found.append(f'{tag} {name}="{value.replace(PLACEHOLDER, "…")}"')

    def handle_endtag(self, tag):
        if tag in ("script", "style") and self._raw:
            self._raw -= 1

    def handle_data(self, data):
        if not self._raw and _words(data):
            self.found.append(" ".join(data.replace(PLACEHOLDER, "…").split()))


def unmarked(path: Path) -> list[str]:
    """The texts of the template at ``path`` that hold words but are not marked for translation."""
    parser = _Texts()
    parser.feed(_rebuilt(path.read_text()))
    parser.close()
    return parser.found


def all_templates() -> list[Path]:
    return sorted(p for p in TEMPLATES.rglob("*") if p.suffix in (".html", ".txt"))


IGNORE = ["locale/*", "tests/*", "docker/*", "var/*", "static/vendor/*", "*/migrations/*"]


def _makemessages(tree: Path, domain: str) -> Path:
    """Run Django's makemessages (GNU xgettext) over ``tree``; the German catalogue it wrote."""
    from django.core.management import call_command
    from django.test import override_settings

    here = os.getcwd()
    os.chdir(tree)
    try:
        with override_settings(LOCALE_PATHS=[str(tree / "locale")]):
            (tree / "locale").mkdir(exist_ok=True)
            extensions = ["js"] if domain == "djangojs" else ["html", "txt", "py"]
            call_command("makemessages", locale=["de"], domain=domain, extensions=extensions, verbosity=0,
                         no_location=False, add_location="file", no_obsolete=True,
                         ignore_patterns=IGNORE)
    finally:
        os.chdir(here)
    return tree / "locale" / "de" / "LC_MESSAGES" / f"{domain}.po"


def extract(files: list[Path], domain: str = "django") -> str:
    """The PO catalogue of the strings ``files`` mark (msgstr empty), as makemessages writes it."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp)
        for file in files:
            target = tree / file.resolve().relative_to(ROOT)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(file, target)
        po = _makemessages(tree, domain)
        return po.read_text() if po.exists() else ""


def entries(po_text: str) -> dict[tuple[str, str], tuple[str, bool]]:
    """{(msgctxt, msgid): (msgstr or the joined plural forms, fuzzy)} of a PO text (header left out)."""
    result: dict[tuple[str, str], tuple[str, bool]] = {}
    for block in re.split(r"\n\s*\n", po_text):
        fields: dict[str, str] = {}
        current = None
        fuzzy = False
        for line in block.splitlines():
            if line.startswith("#,") and "fuzzy" in line:
                fuzzy = True
            if line.startswith("#"):
                continue
            match = re.match(r'^(msgctxt|msgid|msgid_plural|msgstr(?:\[\d+\])?)\s+"(.*)"$', line)
            if match:
                current = match.group(1)
                fields[current] = _unquote(match.group(2))
            elif line.startswith('"') and current:
                fields[current] += _unquote(line[1:-1])
        if "msgid" not in fields or not fields["msgid"]:
            continue
        translated = fields.get("msgstr", "") if "msgid_plural" not in fields else "|".join(
            v for k, v in sorted(fields.items()) if k.startswith("msgstr[") and v)
        if "msgid_plural" in fields and any(k.startswith("msgstr[") and not v for k, v in fields.items()):
            translated = ""
        result[(fields.get("msgctxt", ""), fields["msgid"])] = (translated, fuzzy)
    return result


def _unquote(text: str) -> str:
    """A PO string's escapes (\\n, \\t, \\", \\\\) undone."""
    return re.sub(r"\\(.)", lambda m: _ESCAPES.get(m.group(1), m.group(1)), text)


_ESCAPES = {"n": "\n", "t": "\t", "r": "\r", '"': '"', "\\": "\\"}


def missing(domain: str = "django") -> list[str]:
    """Marked strings of the whole project that the German catalogue does not translate."""
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "project"
        shutil.copytree(ROOT, tree, ignore=shutil.ignore_patterns(".*", "var", "docker", "tests", "locale",
                                                                  "__pycache__", "*.pyc", "artifacts"))
        wanted = entries(_makemessages(tree, domain).read_text())
    committed_path = LOCALE / "de" / "LC_MESSAGES" / f"{domain}.po"
    committed = entries(committed_path.read_text()) if committed_path.exists() else {}
    problems = []
    for key in wanted:
        text, fuzzy = committed.get(key, ("", False))
        if not text or fuzzy:
            problems.append((f"[{key[0]}] " if key[0] else "") + key[1])
    return problems


def update() -> None:
    """The committed catalogues brought up to date with every marked string (makemessages keeps
    the translations they have), the German texts of locale/de/parts/*.po merged in (msgmerge
    compendiums: a translated entry wins over an empty one), and compiled to .mo files."""
    from django.core.management import call_command

    for domain in ("django", "djangojs"):
        po = _makemessages(ROOT, domain)
        parts = [p for p in sorted((LOCALE / "de" / "parts").glob("*.po"))
                 if (p.stem == "js" or p.stem.endswith("-js")) == (domain == "djangojs")]
        if parts:
            # msgmerge prefers the existing catalogue's entry to a compendium's, and counts an
            # empty plural entry as translated: so the existing catalogue goes in with its
            # translated entries only, the rest come from the parts (or stay empty).
            translated, merged = po.with_suffix(".translated"), po.with_suffix(".merged")
            subprocess.run(["msgattrib", "--force-po", "--translated", "--no-fuzzy", "-o", str(translated), str(po)],
                           check=True)
            compendiums = [arg for part in parts for arg in ("--compendium", str(part))]
            subprocess.run(["msgmerge", "--quiet", "--no-fuzzy-matching", *compendiums, "-o", str(merged),
                            str(translated), str(po)], check=True)
            merged.replace(po)
            translated.unlink()
        _set_header(po)
    here = os.getcwd()
    os.chdir(ROOT)
    try:
        call_command("compilemessages", locale=["de"], verbosity=0, ignore_patterns=["docker/*", ".*"])
    finally:
        os.chdir(here)


HEADER = """# German texts of the ROS 2 lifecycle manager (docs/translation.md).
msgid ""
msgstr ""
"Project-Id-Version: ros2-lifecycle-manager\\n"
"Language: de\\n"
"MIME-Version: 1.0\\n"
"Content-Type: text/plain; charset=UTF-8\\n"
"Content-Transfer-Encoding: 8bit\\n"
"Plural-Forms: nplurals=2; plural=(n != 1);\\n"
"""


def _set_header(po: Path) -> None:
    """The catalogue's header as ours (makemessages writes a template's, marked fuzzy, with no
    language and a creation date that would change the file at every run)."""
    text = po.read_text()
    body = text.split("\n\n", 1)[1] if "\n\n" in text else ""
    po.write_text(HEADER + "\n" + body)


def main(argv: list[str]) -> int:
    import django

    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "lifecycle_site.settings")
    django.setup()
    command, files = (argv[0] if argv else ""), [Path(a) for a in argv[1:]]
    if command == "unmarked":
        found = 0
        for path in files or all_templates():
            for text in unmarked(path):
                found += 1
                print(f"{path}: {text}")
        return 1 if found else 0
    if command == "compile":
        from django.template import TemplateSyntaxError
        from django.template.loader import get_template

        bad = 0
        for path in files or all_templates():
            try:
                get_template(str(path.resolve().relative_to(TEMPLATES)))
            except TemplateSyntaxError as error:
                bad += 1
                print(f"{path}: {error}")
        return 1 if bad else 0
    if command == "extract":
        domain = "djangojs" if files and all(f.suffix == ".js" for f in files) else "django"
        sys.stdout.write(extract(files, domain))
        return 0
    if command == "update":
        update()
        gaps = missing("django") + missing("djangojs")
        print(f"{len(gaps)} marked strings without a German text" + (":\n" + "\n".join(gaps) if gaps else ""))
        return 1 if gaps else 0
    if command == "missing":
        gaps = missing("django") + missing("djangojs")
        print("\n".join(gaps))
        return 1 if gaps else 0
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
