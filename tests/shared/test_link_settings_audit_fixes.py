"""Link settings the relay can never accept are refused where they are read (the config
audit): a hello it refuses would be retried for ever; a host name that cannot be encoded
ended the link's task with a UnicodeError; absurd delays were taken as given."""

from __future__ import annotations

from typing import Any

import pytest

from shared.config import resolve_config
from shared.errors import ConfigError
from shared.link_settings import StationLinkConfig, parse_link_url
from shared.protocol.fields import FieldError
from shared.protocol.messages import Hello


@pytest.mark.parametrize(("settings", "said"), [
    ({"session": "lab 1"}, r"^session 'lab 1' is not a session id"),
    ({"session": ""}, r"^session '' is not a session id"),
    ({"session": "-lab"}, r"^session '-lab' is not a session id"),
    ({"session": "s" * 65}, r"^session 's{65}' is not a session id"),
    ({"token": "x" * 513}, r"^token is longer than 512 characters"),
    ({"name": "n" * 65}, r"^name is longer than 64 characters"),
])
def test_a_hello_the_relay_refuses_is_refused_by_name(settings: dict[str, Any],
                                                      said: str) -> None:
    with pytest.raises(ConfigError, match=said) as refused:
        StationLinkConfig(**settings)
    assert "x" * 100 not in str(refused.value)  # a token is never shown
    env = {f"TELETOUCH_REMOTE_LINK_{k.upper()}": v for k, v in settings.items()}
    with pytest.raises(ConfigError, match=r"^\[remote\.link\]: " + said[1:]):
        resolve_config(StationLinkConfig, "remote.link", environ=env)


def test_the_edges_the_relay_accepts_pass_and_agree_with_the_relay() -> None:
    """The limits are the relay's (Hello.from_wire): at them it reads the hello, one
    beyond it refuses it."""
    from shared.link_settings import HELLO_NAME_MAX_CHARS, HELLO_TOKEN_MAX_CHARS

    edge = StationLinkConfig(session="A" + "b_.-" * 15 + "xyz", token="t" * 512,
                             name="n" * 64)
    assert (HELLO_TOKEN_MAX_CHARS, HELLO_NAME_MAX_CHARS) == (512, 64)
    wire = {"role": "local", "session": edge.session, "token": edge.token, "name": edge.name}
    Hello.from_wire(wire)
    for key, too_long in (("token", "t" * 513), ("name", "n" * 65), ("session", "s" * 65)):
        with pytest.raises(FieldError):
            Hello.from_wire({**wire, key: too_long})


@pytest.mark.parametrize("url", ["ws://" + "a" * 70 + ".example/", "tcp://a..b:8766",
                                 "wss://" + "b" * 64 + ":443/"])
def test_a_host_that_cannot_be_looked_up_is_refused(url: str) -> None:
    """Before: accepted, and the link's task died with UnicodeError at its first connect."""
    with pytest.raises(ConfigError, match=r"is not a valid host name \(each dot-separated "
                                          r"label 1 to 63 characters\)"):
        parse_link_url(url)
    with pytest.raises(ConfigError, match=r"^\[local\.link\]: relay URL"):
        resolve_config(StationLinkConfig, "local.link",
                       environ={"TELETOUCH_LOCAL_LINK_URL": url})


def test_hosts_that_can_be_looked_up_pass() -> None:
    for url, host in (("ws://relay.example.org/", "relay.example.org"),
                      ("wss://bücher.example/", "bücher.example"),
                      ("tcp://[::1]:8766", "::1"), ("tls://10.0.0.1:8766", "10.0.0.1"),
                      ("ws://" + "a" * 63 + ".example/", "a" * 63 + ".example")):
        assert parse_link_url(url)[1] == host


@pytest.mark.parametrize("url", ["ws://relayuser:hunter2@127.0.0.1:8765/",
                                 "wss://hunter2@relay.example/", "tcp://u:hunter2@h:1"])
def test_user_information_in_the_url_is_refused_without_showing_it(url: str) -> None:
    with pytest.raises(ConfigError, match=r"holds user information") as refused:
        StationLinkConfig(url=url)
    assert "hunter2" not in str(refused.value) and "***@" in str(refused.value)


def test_a_bad_url_with_a_password_does_not_show_it() -> None:
    for url in ("ws://u:hunter2@h:99999/", "http://u:hunter2@h/"):
        with pytest.raises(ConfigError) as refused:
            parse_link_url(url)
        assert "hunter2" not in str(refused.value)


@pytest.mark.parametrize("url", [
    "ws://user:SECRET/PW@relay.example/",     # a '/' in the password: '@' past the host
    "ws:/user:SECRETPW@relay.example/",       # one slash: no netloc at all
    "ws://user:12345/SECRETPW@relay.example/",  # was taken as host 'user', port 12345
    "wss://user:SECRET@PW@relay.example:443/",  # an '@' in the password
    "tcp://SECRETPW@relay.example:8766",
    "ws://relay.example/SECRETPW@x",
])
def test_a_url_with_an_at_sign_anywhere_is_refused_and_masked(url: str) -> None:
    with pytest.raises(ConfigError, match=r"holds user information") as refused:
        StationLinkConfig(url=url)
    message = str(refused.value)
    assert "SECRET" not in message and "PW" not in message, message
    assert "***@" in message


def test_the_mask_keeps_the_scheme_and_what_follows_the_last_at() -> None:
    from shared.link_settings import _shown_url
    assert _shown_url("ws://user:SECRET/PW@relay.example/") == "ws://***@relay.example/"
    assert _shown_url("ws:/user:SECRETPW@relay.example/") == "ws:***@relay.example/"
    assert _shown_url("user:pw/x@relay.example") == "user:***@relay.example"
    assert _shown_url("pw/x@relay.example") == "***@relay.example"
    assert _shown_url("wss://relay.example:443/path") == "wss://relay.example:443/path"


@pytest.mark.parametrize(("settings", "said"), [
    ({"reconnect_max_s": 1e9}, r"^reconnect_max_s \(1000000000\.0\) must be <= 60 s"),
    ({"reconnect_max_s": 60.5}, r"^reconnect_max_s \(60\.5\) must be <= 60 s"),
    ({"liveness_timeout_s": 1e9}, r"^liveness_timeout_s \(1000000000\.0\) must be <= 60 s"),
    ({"connect_timeout_s": 3600.0}, r"^connect_timeout_s \(3600\.0\) must be <= 60 s"),
])
def test_absurd_link_delays_are_refused(settings: dict[str, Any], said: str) -> None:
    with pytest.raises(ConfigError, match=said):
        StationLinkConfig(**settings)


def test_the_defaults_and_the_edges_of_the_delays_pass() -> None:
    StationLinkConfig()
    StationLinkConfig(reconnect_min_s=60.0, reconnect_max_s=60.0, connect_timeout_s=60.0,
                      liveness_timeout_s=60.0)
