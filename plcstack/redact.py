"""Secrets in a configuration text: hidden when it is shown, put back when an edited copy returns.

A configuration file holds secrets in few places (the OPC UA users' ``password_hash``; a
password in a URL, ``mqtt://user:PASSWORD@host``, which the tables refuse but an edited file
may still carry), and a face that shows the running file (the web console's ``GET
/api/config``) must never show one. Which values are secret is decided on what tomllib reads,
not on how the text spells it: a key quoted, escaped (``"password\\u005fhash"``), dotted, in an
inline table or an array of tables, a value in any of TOML's four string forms, are all the same
key and value to the parser, so no spelling hides one. Every string of the text (keys included)
is decoded with tomllib itself and rewritten where it holds a secret; a comment or bare text
holding one is rewritten too; and the result is checked before it is returned: parsed again,
no secret value is left anywhere in it, else :class:`RedactionError` (nothing is shown).

A secret is replaced by a marker ``<redacted:ID>``, where ID is a keyed hash of the secret with a
key drawn when the process starts: it says which secret stood there without saying anything
about it, so :func:`restore` can put the running secret back when a text shown by this process
comes back with its markers (edit the file, keep the secrets you cannot see). A marker this
process did not hand out (an older process's, a secret changed meanwhile) is refused with its
line: a text is never written with a marker standing where a secret was.
"""

from __future__ import annotations

import functools
import hashlib
import hmac
import re
import secrets
import tomllib
from collections.abc import Callable, Iterator
from typing import Final

from plcstack.tomlfile import toml_string

__all__ = [
    "MARKER",
    "RedactionError",
    "is_secret_key",
    "redact",
    "restore",
    "secrets_of",
]

#: a redacted secret in a shown text
MARKER: Final = re.compile(r"<redacted:([0-9a-f]{12})>")
#: words that make a key's value a secret, whatever table it is in
_SECRET_WORDS: Final = ("password", "passwd", "passphrase", "secret", "token", "credential")
#: suffixes of keys that say where a secret is, not what it is (shown: an operator needs them)
_WHERE_SUFFIXES: Final = ("_env", "_file", "_path", "_dir")
#: ``scheme://user:PASSWORD@``: the password of a URL's user information
_URL_PASSWORD: Final = re.compile(r"([A-Za-z][A-Za-z0-9+.\-]*://[^\s/@:]*:)([^\s/@]+)(?=@)")
#: secrets at least this long are also looked for inside other text (comments, other strings);
#: a shorter one only where it is a secret's whole value or a URL's password
_SEARCHED: Final = 4
#: the key of the markers' hash: new in every process, so a marker cannot be checked against
#: guesses of the secret anywhere else
_KEY: Final = secrets.token_bytes(32)


class RedactionError(ValueError):
    """A text that cannot be shown redacted (a secret this module could not find the text of),
    or returned with markers that cannot be put back (:func:`restore`): the message says which
    and where, never the secret."""


@functools.lru_cache(maxsize=4096)  # a plant's file repeats a few key names many times
def is_secret_key(name: str) -> bool:
    """Whether a key's value is a secret: ``password_hash``, and any key named like a password,
    token, secret or credential in any case (``Password``, ``api-token``), but not one that
    names where a secret is kept (``password_env``, ``key_file``)."""
    key = name.lower().replace("-", "_")
    if key.endswith(_WHERE_SUFFIXES):
        return False
    return any(word in key for word in _SECRET_WORDS)


def secrets_of(data: dict[str, object]) -> frozenset[str]:
    """Every secret of a parsed configuration: the values of secret keys (:func:`is_secret_key`,
    every string under one) and the passwords of URLs in any string value."""
    found: set[str] = set()
    stack: list[tuple[object, bool]] = [(data, False)]
    while stack:
        node, secret = stack.pop()
        if isinstance(node, dict):
            stack.extend((value, secret or is_secret_key(str(key))) for key, value in node.items())
        elif isinstance(node, list):
            stack.extend((value, secret) for value in node)
        elif isinstance(node, str):
            if secret and node:
                found.add(node)
            found.update(m.group(2) for m in _URL_PASSWORD.finditer(node))
        elif secret:
            found.add(str(node))  # not a string: the tables refuse it, the check below finds it
    return frozenset(found)


def _marker(secret: str) -> str:
    digest = hmac.new(_KEY, secret.encode("utf-8", "surrogatepass"), hashlib.sha256)
    return f"<redacted:{digest.hexdigest()[:12]}>"


def redact(text: str) -> str:
    """``text`` with every secret replaced by its marker; :class:`RedactionError` if ``text``
    is not TOML (its secrets cannot be told) or a secret would still show."""
    data = _parse(text, "the configuration")
    found = secrets_of(data)
    if not found:
        return text
    markers = {secret: _marker(secret) for secret in found}
    # one pass over each text, longest secret first: a marker put in is never searched again
    searched = sorted((s for s in found if len(s) >= _SEARCHED), key=len, reverse=True)
    inside = re.compile("|".join(map(re.escape, searched))) if searched else None

    def url(m: re.Match[str]) -> str:
        password = m.group(2)
        return m.group(0) if MARKER.fullmatch(password) else m.group(1) + _marker(password)

    def hide(value: str, line: int) -> str:
        if value in markers:
            return markers[value]
        if inside is not None:
            value = inside.sub(lambda m: markers[m.group(0)], value)
        return _URL_PASSWORD.sub(url, value)

    shown = _rewrite(text, hide, bare=False)
    _check(shown, found)
    return shown


def restore(text: str, running: str, *, source: str = "the text") -> str:
    """``text`` with each marker replaced by the secret of ``running`` (the configuration whose
    redacted text was shown) it stands for. :class:`RedactionError` naming ``source``'s lines
    if a marker stands for no secret of ``running`` (the text was shown by another process, or
    the secret changed since) or one is left where it cannot be replaced."""
    known: dict[str, str] | None = None  # marker -> secret, read at the first marker
    unknown: list[str] = []

    def put_back(value: str, line: int) -> str:
        def one(m: re.Match[str]) -> str:
            nonlocal known
            if known is None:
                running_secrets = secrets_of(_parse(running, "the running configuration"))
                known = {_marker(s): s for s in running_secrets}
            secret = known.get(m.group(0))
            if secret is None:
                unknown.append(
                    f"{source}:{line}: {m.group(0)} stands for no secret of the running"
                    " configuration (it was shown by an earlier run, or the secret changed"
                    " since): read the configuration again, or write the secret itself"
                )
                return m.group(0)
            return secret

        return MARKER.sub(one, value)

    restored = _rewrite(text, put_back, bare=True)
    if unknown:
        raise RedactionError("\n".join(unknown))
    try:
        data = tomllib.loads(restored)
    except (tomllib.TOMLDecodeError, RecursionError):
        data = None  # the loader says what is wrong with it, with its line
    left = [m.group(0) for m in MARKER.finditer(restored)]
    if data is not None:
        left += [m.group(0) for s in _strings(data) for m in MARKER.finditer(s)]
    if left:
        raise RedactionError(
            f"{source}: {left[0]} is left where the console cannot put its secret back (it is"
            " not a whole TOML string, comment or bare text of its own): write the secret itself"
        )
    return restored


def _parse(text: str, what: str) -> dict[str, object]:
    try:
        return tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise RedactionError(f"{what} is not TOML ({exc}); it cannot be shown redacted") from None


def _check(shown: str, found: frozenset[str]) -> None:
    """Raise unless ``shown`` parses and no secret is left in it: a secret-key value is a
    marker (or empty), no URL password is anything but a marker, no searched secret is found
    in a comment or in any decoded string or key (markers aside)."""
    try:
        data = tomllib.loads(shown)
    except (tomllib.TOMLDecodeError, RecursionError):
        raise RedactionError(
            "a secret stands where replacing it would break the file (a bare key or number):"
            " the configuration is not shown"
        ) from None
    searched = [s for s in found if len(s) >= _SEARCHED]
    stack: list[tuple[object, bool]] = [(data, False)]
    while stack:
        node, secret = stack.pop()
        if isinstance(node, dict):
            for key, value in node.items():
                if any(s in key for s in searched):
                    raise RedactionError(
                        "a secret is also a key name: the configuration is not shown"
                    )
                stack.append((value, secret or is_secret_key(key)))
        elif isinstance(node, list):
            stack.extend((value, secret) for value in node)
        elif isinstance(node, str):
            plain = MARKER.sub("", node)
            if (
                (secret and plain)
                or _URL_PASSWORD.search(plain)
                or any(s in plain for s in searched)
            ):
                raise RedactionError(
                    "a secret could not be replaced: the configuration is not shown"
                )
        elif secret:
            raise RedactionError(
                "a secret key holds a value that is not a string: the configuration is not shown"
            )
    comments = [MARKER.sub("", shown[a:b]) for kind, a, b in _tokens(shown) if kind == "comment"]
    if any(s in c for s in searched for c in comments):
        raise RedactionError("a secret could not be replaced: the configuration is not shown")


def _strings(data: object) -> Iterator[str]:
    """Every string of parsed TOML, keys included."""
    stack = [data]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            yield from (str(k) for k in node)
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
        elif isinstance(node, str):
            yield node


# -- the text, token by token ---------------------------------------------------------------------
def _rewrite(text: str, change: Callable[[str, int], str], *, bare: bool) -> str:
    """``text`` with ``change(value, line)`` applied to the decoded value of every string
    (re-encoded where it changed), to the raw text of every comment and, with ``bare``, to the
    bare text between them (keys, numbers, brackets)."""
    out: list[str] = []
    line = 1
    for kind, start, end in _tokens(text):
        raw = text[start:end]
        value = _decode(raw) if kind == "string" else None
        if kind == "bare" and not bare:
            out.append(raw)
        elif value is None:  # a comment, bare text, or a string the parser does not take
            out.append(change(raw, line))
        else:
            changed = change(value, line)
            out.append(raw if changed == value else _encode(changed, raw))
        line += raw.count("\n")
    return "".join(out)


#: a string in any of TOML's four forms (a multi-line one with the up to two quotes before its
#: closing three that belong to its content), or a comment
_TOKEN: Final = re.compile(
    r'(?P<string>"""(?:[^"\\]|\\.|"(?!""))*"""(?:"{1,2})?'
    r"|'''[\s\S]*?'''(?:'{1,2})?"
    r'|"(?:[^"\\\n]|\\.)*"'
    r"|'[^'\n]*')"
    r"|(?P<comment>#[^\n]*)",
    re.S,
)


def _tokens(text: str) -> Iterator[tuple[str, int, int]]:
    """``(kind, start, end)`` of each string (any of TOML's four forms), comment and stretch of
    bare text between them, in order, covering ``text``."""
    bare = 0
    for m in _TOKEN.finditer(text):
        start, end = m.span()
        if bare < start:
            yield "bare", bare, start
        yield ("string" if m.group("string") is not None else "comment"), start, end
        bare = end
    if bare < len(text):
        yield "bare", bare, len(text)


def _decode(raw: str) -> str | None:
    """A string token's value as tomllib reads it; None if it is not one. A one-line string
    without a backslash is its text between the quotes; any other is read by tomllib."""
    if raw[:3] not in ('"""', "'''") and "\\" not in raw:
        return raw[1:-1]
    try:
        value = tomllib.loads("v = " + raw).get("v")
    except (tomllib.TOMLDecodeError, RecursionError):
        return None
    return value if isinstance(value, str) else None


def _encode(value: str, like: str) -> str:
    """``value`` as a TOML string: in ``'...'`` if ``like`` was one and it can be (the text
    reads as before around it), else a basic string with every character TOML forbids
    there escaped."""
    if like.startswith("'") and not like.startswith("'''") and _LITERAL_OK.fullmatch(value):
        return f"'{value}'"
    return toml_string(value)


#: what a one-line literal string may hold (no quote, no control character)
_LITERAL_OK: Final = re.compile(r"[^'\x00-\x08\x0a-\x1f\x7f]*")
