"""Version-2 tokens bound to session, role and expiry (issue 11 item 2)."""

from __future__ import annotations

import logging
import subprocess
import sys
import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from relay_server.auth import TokenAuthority, derive_token, make_token
from shared.errors import AuthError, ConfigError, TokenExpiredError
from shared.protocol import Hello
from tests.relay_server.relay_clients import SECRET, clients, running_relay


def test_v2_token_binds_session_role_and_expiry() -> None:
    auth = TokenAuthority({}, "s3cret")
    tok = make_token("s3cret", "lab1", "local", 2_000)
    auth.check("lab1", tok, "local", now_s=1_999)
    with pytest.raises(AuthError, match="role 'local', not 'remote'"):
        auth.check("lab1", tok, "remote", now_s=1_999)
    with pytest.raises(AuthError, match="wrong token"):
        auth.check("lab2", tok, "local", now_s=1_999)
    with pytest.raises(TokenExpiredError, match=r"expired at 2000 .*1 s ago"):
        auth.check("lab1", tok, "local", now_s=2_001)
    with pytest.raises(AuthError, match="wrong token"):  # another secret
        auth.check("lab1", make_token("other", "lab1", "local", 2_000), "local", now_s=1)
    forged_role = tok.replace("v2.local.", "v2.remote.")
    with pytest.raises(AuthError, match="wrong token"):
        auth.check("lab1", forged_role, "remote", now_s=1)
    forged_expiry = tok.replace(".2000.", ".9999999999.")
    with pytest.raises(AuthError, match="wrong token"):
        auth.check("lab1", forged_expiry, "local", now_s=1)
    with pytest.raises(ConfigError):
        make_token("s3cret", "lab1", "pilot", 1)


@settings(max_examples=60, deadline=None)
@given(junk=st.text(max_size=80))
def test_garbage_v2_tokens_are_refused_not_crashing(junk: str) -> None:
    auth = TokenAuthority({}, "s3cret")
    with pytest.raises(AuthError):
        auth.check("lab1", "v2." + junk, "local", now_s=0)


def test_legacy_tokens_only_when_allowed() -> None:
    legacy = derive_token("s3cret", "lab1")
    TokenAuthority({"t": "tab"}, "s3cret").check("lab1", legacy, "remote")
    strict = TokenAuthority({"t": "tab"}, "s3cret", allow_legacy=False)
    for tok, session in ((legacy, "lab1"), ("tab", "t")):
        with pytest.raises(AuthError, match="legacy"):
            strict.check(session, tok, "local")
    strict.check("lab1", make_token("s3cret", "lab1", "observer", int(time.time()) + 60),
                 "observer")
    with pytest.raises(ConfigError):
        TokenAuthority({"t": "tab"}, None, allow_legacy=False)


@pytest.mark.parametrize("kind", ["ws", "tcp"])
async def test_relay_refuses_wrong_role_and_expired_tokens_with_auth_4001(
        kind: str, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    now = int(time.time())
    local_tok = make_token(SECRET, "v2s", "local", now + 600)
    expired = make_token(SECRET, "v2s", "remote", now - 1)
    async with running_relay(allow_legacy_tokens=False) as relay, clients(
            (kind, 0), (kind, 0), (kind, 0), (kind, 0)) as (local, as_remote, late, legacy):
        for c in (local, as_remote, late, legacy):
            await c.connect(relay)
        await local.hello("local", "v2s", token=local_tok)
        for client, tok, why in ((as_remote, local_tok, "not 'remote'"),
                                 (late, expired, "expired"),
                                 (legacy, derive_token(SECRET, "v2s"), "legacy")):
            await client.send(Hello(role="remote", session="v2s", token=tok))
            err = await client.expect("error")
            # an expired token says so in `reason` (a station whose clock calls it valid
            # retries: tests/shared/test_client_faults.py); an older station reads `auth`
            assert (err.code, err.fatal) == ("auth", True) and why in err.message, err
            assert err.reason == ("expired" if why == "expired" else None)
            got = await client.expect_closed()
            if kind == "ws":
                assert got == 4001
        logs = "\n".join(r.getMessage() for r in caplog.records)
        assert "expired" in logs
        for tok in (local_tok, expired, local_tok.rsplit(".", 1)[1]):
            assert tok not in logs


def test_print_token_with_role_and_ttl() -> None:
    def run(*args: str) -> str:
        out = subprocess.run([sys.executable, "-m", "lab.cli", "relay", "--secret", "k" * 32,
                              "--print-token", "lab1", *args], capture_output=True,
                             text=True, check=True)
        return out.stdout.strip()

    before = int(time.time())
    tok = run("--role", "remote", "--ttl-s", "60")
    version, role, expiry, _ = tok.split(".")
    assert (version, role) == ("v2", "remote")
    assert before + 60 <= int(expiry) <= int(time.time()) + 60
    TokenAuthority({}, "k" * 32).check("lab1", tok, "remote")
    assert run() == derive_token("k" * 32, "lab1")
