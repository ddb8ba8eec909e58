"""The play server answers its own page and scripts on this machine only (``play.guard``): a foreign ``Host`` (a
DNS-rebinding page) is a 421, a foreign ``Origin`` may neither POST nor open the websocket, a body is JSON of at
most 64 KiB (refused before it is read whole), nesting is bounded, and a binary websocket message is an error reply
that leaves the connection open; names from a corpus reach the page as text, never markup. A real server on loopback
over a replay session of the test corpus, and Debian's Chromium for the page."""

from __future__ import annotations

import http.client
import json
import shutil

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from marionette.cli import main
from marionette.corpus import Corpus
from marionette.play import make_session
from marionette.play.access import TOKEN as TOKEN_PATTERN
from marionette.play.access import access
from marionette.play.guard import MAX_BODY, parse_message
from marionette.play.server import Server

pytestmark = pytest.mark.quality  # real servers and a browser


@pytest.fixture(scope="module")
def server(corpus):
    segment = Corpus(corpus).segment_ids()[0]
    session = make_session(None, None, replay=corpus, segment=segment, size=(36, 64), log=lambda *_: None)
    srv = Server(session, port=0, fps=5, log=lambda *_: None).start()
    yield srv
    srv.stop()


def request(srv, method: str, path: str, body: bytes | None = None, headers: dict | None = None) -> tuple[int, dict]:
    """(status, JSON) of one request on a fresh connection."""
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=30)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        r = conn.getresponse()
        return r.status, json.loads(r.read() or b"{}")
    finally:
        conn.close()


def own(srv) -> str:
    return f"127.0.0.1:{srv.port}"


def test_a_foreign_host_is_refused_and_the_loopback_names_answer(server):
    code, body = request(server, "GET", "/api/status", headers={"Host": f"evil.example:{server.port}"})
    assert code == 421 and "evil.example" in body["error"]
    for host in (own(server), f"localhost:{server.port}"):
        assert request(server, "GET", "/api/status", headers={"Host": host})[0] == 200


def test_a_foreign_origin_may_not_post_and_a_body_is_json(server):
    pause = json.dumps({"paused": True}).encode()
    kinds = {"Content-Type": "application/json"}
    code, body = request(server, "POST", "/api/pause", pause, {**kinds, "Origin": "http://evil.example"})
    assert code == 403 and "evil.example" in body["error"]
    code, body = request(server, "POST", "/api/pause", pause, {"Content-Type": "text/plain"})
    assert code == 415 and "text/plain" in body["error"]
    assert request(server, "POST", "/api/pause", pause, {**kinds, "Origin": f"http://{own(server)}"})[0] == 200
    assert request(server, "POST", "/api/pause", pause, kinds)[0] == 200  # a script sends no Origin


def test_a_large_body_is_refused_before_it_is_read(server):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    conn.putrequest("POST", "/api/pause")
    conn.putheader("Content-Type", "application/json")
    conn.putheader("Content-Length", str(300 << 20))
    conn.endheaders()  # 300 MB declared, none sent: the answer comes without waiting for them
    r = conn.getresponse()
    assert r.status == 413 and str(MAX_BODY) in json.loads(r.read())["error"]
    conn.close()
    chunks = (b" " * (16 << 10) for _ in range(64))  # 1 MiB sent chunked, without a length
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=30)
    try:
        conn.request("POST", "/api/pause", body=chunks, headers={"Content-Type": "application/json"}, encode_chunked=True)
        r = conn.getresponse()
        assert r.status == 413
    except (BrokenPipeError, ConnectionResetError):
        pass  # the server answered and closed while the rest was still being sent
    finally:
        conn.close()


def test_deep_nesting_is_a_400_not_a_crash(server):
    deep = ("[" * 5000 + "]" * 5000).encode()
    code, body = request(server, "POST", "/api/pause", deep, {"Content-Type": "application/json"})
    assert code == 400 and "nested" in body["error"]
    with pytest.raises(ValueError, match="nested"):
        parse_message('{"a": ' + "[" * 40 + "]" * 40 + "}")
    assert parse_message('{"name": "[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[["}') == {"name": "[" * 38}  # text, not nesting


def test_the_websocket_takes_its_own_page_only_and_survives_a_binary_message(server):
    url = f"ws://{own(server)}/ws"
    with pytest.raises(InvalidStatus) as err:
        connect(url, origin="http://evil.example", open_timeout=30).close()
    assert err.value.response.status_code == 403
    with connect(url, origin=f"http://{own(server)}", open_timeout=30, max_size=None) as ws:
        ws.send(b"\x00binary")
        ws.send(json.dumps({"type": "pause", "seq": 7, "paused": True}))
        replies = []
        while len(replies) < 2:
            msg = ws.recv(timeout=30)
            if isinstance(msg, str) and json.loads(msg)["type"] in ("reply", "error"):
                replies.append(json.loads(msg))
    assert replies[0]["type"] == "error" and "binary" in replies[0]["message"]
    assert replies[1] == {"type": "reply", "seq": 7, "result": {"paused": True}}


def test_names_from_a_corpus_reach_the_page_as_text(browser, corpus, tmp_path):
    evil = '<img src=x onerror="window.pwned = 1"><b>bold</b>'
    copy = tmp_path / "corpus"
    shutil.copytree(corpus, copy)
    vocab_file = copy / "meta" / "vocab.json"
    vocab = json.loads(vocab_file.read_text())
    for entity_type in vocab["entity_types"].values():
        for action in entity_type["actions"]:
            if action["token"]:
                action["name"] = evil  # every action the page names is markup now
    vocab_file.write_text(json.dumps(vocab))
    segment = Corpus(copy).segment_ids()[0]
    session = make_session(None, None, replay=copy, segment=segment, size=(36, 64), log=lambda *_: None)
    srv = Server(session, port=0, fps=10, log=lambda *_: None).start()
    pg = browser.new_page()
    try:
        pg.goto(f"http://127.0.0.1:{srv.port}/")
        pg.wait_for_function("window.marionette && window.marionette.ready && window.marionette.frames >= 3", timeout=60_000)
        shown = pg.inner_text("#entities")
        assert evil in shown  # the name is there, as text
        assert pg.locator("#entities img, #entities b").count() == 0 and pg.locator("img").count() == 0
        assert pg.evaluate("window.pwned") is None
    finally:
        pg.close()
        srv.stop()


TOKEN = "a-test-token-0123456789"


@pytest.fixture(scope="module")
def tokened(corpus):
    """A server bound to every interface, as ``marionette play --host 0.0.0.0 --token ...`` starts it."""
    segment = Corpus(corpus).segment_ids()[0]
    session = make_session(None, None, replay=corpus, segment=segment, size=(36, 64), log=lambda *_: None)
    srv = Server(session, port=0, fps=5, log=lambda *_: None, host="0.0.0.0", token=TOKEN).start()
    yield srv
    srv.stop()


def raw(srv, method: str, path: str, headers: dict | None = None, body: bytes | None = None) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection("127.0.0.1", srv.port, timeout=30)
    conn.request(method, path, body=body, headers=headers or {})
    r = conn.getresponse()
    r.read()
    conn.close()
    return r


def test_off_loopback_every_request_carries_the_token(tokened):
    assert TOKEN in tokened.url and any(TOKEN in u for u in tokened.urls)
    r = raw(tokened, "GET", "/api/status")
    assert r.status == 401
    assert raw(tokened, "GET", "/api/status", {"Authorization": "Bearer wrong-token-0123456789"}).status == 401
    assert raw(tokened, "GET", "/api/status", {"Authorization": f"Bearer {TOKEN}"}).status == 200
    assert raw(tokened, "GET", "/api/status", {"Authorization": f"Bearer {TOKEN}", "Host": "player.lan:1"}).status == 200
    page = raw(tokened, "GET", f"/?token={TOKEN}")  # the printed URL: the page, and the token as its cookie
    cookie = page.getheader("set-cookie")
    assert page.status == 200 and TOKEN in cookie and "HttpOnly" in cookie and "SameSite=Strict" in cookie
    jar = {"Cookie": cookie.split(";")[0]}
    assert raw(tokened, "GET", "/api/status", jar).status == 200
    pause = json.dumps({"paused": True}).encode()
    kinds = {**jar, "Content-Type": "application/json"}
    assert raw(tokened, "POST", "/api/pause", {**kinds, "Origin": "http://evil.example"}, pause).status == 403
    assert raw(tokened, "POST", "/api/pause", {**kinds, "Origin": f"http://127.0.0.1:{tokened.port}"}, pause).status == 200
    url = f"ws://127.0.0.1:{tokened.port}/ws"
    with pytest.raises(InvalidStatus) as err:
        connect(url, open_timeout=30).close()
    assert err.value.response.status_code == 403
    with connect(url, additional_headers=jar, open_timeout=30, max_size=None) as ws:
        ws.send(json.dumps({"type": "pause", "seq": 1, "paused": False}))
        while not (isinstance(msg := ws.recv(timeout=30), str) and json.loads(msg)["type"] == "reply"):
            pass


def test_another_interface_without_a_token_is_refused_before_anything_loads(corpus, capsys):
    assert access("127.0.0.1", None) is None and access("localhost", TOKEN) == TOKEN
    assert TOKEN_PATTERN.fullmatch(access("0.0.0.0", "auto"))
    with pytest.raises(ValueError, match="--host 0.0.0.0 serves other machines: give --token"):
        access("0.0.0.0", None)
    assert main(["play", "--replay", str(corpus), "--host", "0.0.0.0", "--port", "0"]) == 2
    assert "--token" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["play", "--replay", str(corpus), "--host", "0.0.0.0", "--token", "short"])
    assert "16 to 256" in capsys.readouterr().err
