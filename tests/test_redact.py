"""Secrets of a configuration text are redacted whatever the spelling, and put back when the
redacted text comes back (plcstack.redact, behind ``GET``/``POST /api/config``)."""

from __future__ import annotations

import json
import re
import tomllib

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from plcstack.redact import MARKER, RedactionError, is_secret_key, redact, restore

HASH = "pbkdf2_sha256$200000$c2FsdA$aGFzaA"


def strings(data: object) -> list[str]:
    """Every string of parsed TOML, keys included."""
    out: list[str] = []
    stack = [data]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            out.extend(node)
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
        elif isinstance(node, str):
            out.append(node)
    return out


def assert_hidden(text: str, secret: str) -> str:
    """``redact(text)``, checked: the secret is nowhere in it, raw or decoded, and putting the
    secrets back gives the same configuration."""
    shown = redact(text)
    assert secret not in shown
    assert not any(secret in s for s in strings(tomllib.loads(shown)))
    assert MARKER.search(shown)
    assert tomllib.loads(restore(shown, text)) == tomllib.loads(text)
    return shown


# every way TOML lets a file say "the password_hash of the user alice is HASH"
SPELLINGS = [
    f'[opcua.users.alice]\npassword_hash = "{HASH}"\nwrite = true\n',
    f"[opcua.users.alice]\npassword_hash = '{HASH}'\n",
    f'[opcua.users.alice]\n"password_hash" = "{HASH}"\n',
    f"[opcua.users.alice]\n'password_hash' = '{HASH}'\n",
    f'[opcua.users.alice]\n"password\\u005fhash" = "{HASH}"\n',
    f'[opcua.users.alice]\n"\\u0070assword_hash" = "{HASH}"\n',
    f'[opcua.users.alice]\npassword_hash="{HASH}"#c\n',
    f'[opcua.users.alice]\n  password_hash   =   "{HASH}"   # the hash\n',
    f'[opcua]\nusers.alice.password_hash = "{HASH}"\n',
    f'[opcua]\nusers . alice . "password_hash" = "{HASH}"\n',
    f'opcua.users.alice.password_hash = "{HASH}"\n',
    f'[opcua.users]\nalice = {{ password_hash = "{HASH}", write = true }}\n',
    f'[opcua]\nusers = {{ alice = {{ password_hash = "{HASH}" }} }}\n',
    f'[opcua.users.alice]\npassword_hash = """{HASH}"""\n',
    f'[opcua.users.alice]\npassword_hash = """\n{HASH}"""\n',
    f"[opcua.users.alice]\npassword_hash = '''{HASH}'''\n",
    f"[opcua.users.alice]\npassword_hash = '''\n{HASH}'''\n",
    f'[opcua.users.alice]\npassword_hash = "{HASH[:9]}\\u0024{HASH[10:]}"\n',
    '[opcua.users.alice]\npassword_hash = "' + "".join(f"\\u{ord(c):04x}" for c in HASH) + '"\n',
    f'[opcua.users.alice]\npassword_hash = """{HASH[:12]}\\\n    {HASH[12:]}"""\n',
    # any key named like a secret, in any case, anywhere
    f'[opcua.users.alice]\nPassword_Hash = "{HASH}"\n',
    f'[mqtt]\npassword = "{HASH}"\n',
    f'[x]\napi-token = "{HASH}"\n',
    f'[[plc]]\nname = "a"\n[plc.extra]\nclient_secret = "{HASH}"\n',
    f'[[gateway]]\nsecrets = ["{HASH}"]\n',
    # a password in a URL, in any string
    f'[mqtt]\nurl = "mqtt://bob:{HASH}@broker:1883"\n',
    f"[[plc]]\nname = 'a'\nurl = 's5lan://u:{HASH}@10.0.0.5:1'\n",
]


@pytest.mark.parametrize("text", SPELLINGS)
def test_no_spelling_hides_a_secret_from_the_redaction(text: str) -> None:
    assert_hidden(text, HASH)


def test_a_secret_is_also_redacted_where_it_is_repeated_in_a_comment_or_another_string() -> None:
    text = (
        "# the old hash was " + HASH + "\n"
        f"[opcua.users.alice]\npassword_hash = '{HASH}'\n"
        f'[[plc]]\nname = "a"\ndescription = "copied: {HASH}!"\n'
    )
    shown = assert_hidden(text, HASH)
    assert shown.count(MARKER.search(shown).group(0)) == 3  # type: ignore[union-attr]


def test_what_is_not_a_secret_is_shown_as_written() -> None:
    text = (
        "# the plant\n[mqtt]\nurl = 'mqtts://broker:8883'\npassword_env = \"MQTT_PASSWORD\"\n"
        'username_env = "MQTT_USER"\nkey_file = "client.key"\n'
        '[web]\nwrite_token_env = "PLCSTACK_WEB_TOKEN"\n'
        '[opcua]\nprivate_key = "server-key.pem"\n'
    )
    assert redact(text) == text
    for name in ("password_env", "write_token_env", "key_file", "private_key", "buffer_path"):
        assert not is_secret_key(name), name
    for name in ("password_hash", "Password", "api-token", "TOKEN", "passphrase"):
        assert is_secret_key(name), name


def test_the_shown_text_keeps_its_form_and_comes_back_byte_for_byte() -> None:
    text = (
        "# plant 7\n[opcua.users.alice]  # the operator\n"
        f"password_hash = '{HASH}'\nwrite = true\n\n"
        '[opcua.users.bob]\npassword_hash = "pbkdf2_sha256$1$YQ$Yg"\n'
    )
    shown = redact(text)
    assert shown.splitlines()[0:2] == text.splitlines()[0:2]
    assert re.fullmatch(r"password_hash = '<redacted:[0-9a-f]{12}>'", shown.splitlines()[2])
    assert restore(shown, text) == text


def test_a_marker_this_run_did_not_hand_out_is_refused_with_its_line() -> None:
    text = f"[opcua.users.alice]\npassword_hash = '{HASH}'\n"
    shown = redact(text)
    other = shown.replace(MARKER.search(shown).group(1), "0123456789ab")  # type: ignore[union-attr]
    with pytest.raises(RedactionError) as err:
        restore(other, text, source="/etc/plcstack/plant.toml")
    assert str(err.value).startswith("/etc/plcstack/plant.toml:2: <redacted:0123456789ab>")
    # a secret changed since the text was shown: its marker stands for nothing running now
    with pytest.raises(RedactionError):
        restore(shown, text.replace("200000", "300000"))


def test_an_escaped_marker_is_put_back_too() -> None:
    """A marker written with TOML escapes still stands for the secret: it is never written as
    the text of a password_hash."""
    text = f"[opcua.users.alice]\npassword_hash = '{HASH}'\n"
    marker = MARKER.search(redact(text)).group(0)  # type: ignore[union-attr]
    escaped = "".join(f"\\u{ord(c):04x}" for c in marker)
    back = restore(f'[opcua.users.alice]\npassword_hash = "{escaped}"\n', text)
    assert tomllib.loads(back)["opcua"]["users"]["alice"]["password_hash"] == HASH


def test_a_text_that_is_not_toml_is_not_shown() -> None:
    with pytest.raises(RedactionError, match="not TOML"):
        redact(f'password = "{HASH}"\n[[[')


def test_a_secret_that_is_also_a_bare_key_is_not_shown() -> None:
    with pytest.raises(RedactionError):
        redact("[mqtt]\nurl = 'mqtt://u:abcd1234@h'\n[abcd1234]\nx = 1\n")


_SECRET = st.text(
    st.characters(exclude_categories=["Cs"], min_codepoint=1), min_size=1, max_size=24
).filter(lambda s: "\n" not in s)


def _spell(secret: str, form: int) -> str | None:
    """``secret`` as a TOML value in one of its forms (None where that form cannot hold it)."""
    if form == 0:
        return json.dumps(secret, ensure_ascii=False).replace("\x7f", "\\u007f")
    if form == 1:
        return "".join(f"\\U{ord(c):08x}" for c in secret).join('""')
    controls = any((ord(c) < 32 and c != "\t") or ord(c) == 0x7F for c in secret)
    if form == 2 and "'" not in secret and not controls:
        return f"'{secret}'"
    if form == 3 and "'''" not in secret and not secret.endswith("'") and not controls:
        return f"'''{secret}'''"
    return None


@settings(max_examples=300, deadline=None)
@given(secret=_SECRET, form=st.integers(0, 3), key=st.sampled_from(["password_hash", "token"]))
def test_any_secret_in_any_string_form_is_redacted_and_put_back(
    secret: str, form: int, key: str
) -> None:
    value = _spell(secret, form)
    if value is None:
        return
    text = f'[opcua.users.alice]\n{key} = {value}\nwrite = true\n[[plc]]\nname = "p"\n'
    # a secret that is also a key's name cannot be hidden: such a file is not shown at all
    assume(not any(secret in k for k in ("opcua", "users", "alice", key, "write", "plc", "name")))
    shown = redact(text)
    assert tomllib.loads(shown)["opcua"]["users"]["alice"][key].startswith("<redacted:")
    if len(secret) >= 4:  # not in any string or key (a shorter one: where it is the secret)
        assert not any(secret in MARKER.sub("", s) for s in strings(tomllib.loads(shown)))
    assert tomllib.loads(restore(shown, text)) == tomllib.loads(text)
