"""The page's teleoperation client (static/js/teleop.js) against a scripted socket in the page: what it sends when
the server refuses a message, without a participant or a server-side arm."""

from __future__ import annotations

#: A stand-in for the browser's WebSocket: records what the page sends; the test plays the server's part.
FAKE_SOCKET = """
window.sent = [];
window.FakeSocket = class {
  static OPEN = 1;
  constructor(url) {
    this.url = url; this.readyState = 1; window.socket = this;
    setTimeout(() => this.onopen && this.onopen(), 0);
  }
  send(text) { window.sent.push(JSON.parse(text)); }
  close() { this.readyState = 3; }
  serve(message) { this.onmessage({ data: JSON.stringify(message) }); }
};
window.WebSocket = window.FakeSocket;
"""

HELLO = {"type": "hello", "teleop": {
    "time_left_ms": 60_000, "guidance": {},
    "world": {"gripper_target": 0.1}, "scene": {},
    "limits": {"rate_limit_hz": 60, "keepalive_s": 0.2}}}


def test_an_input_the_rate_limit_refused_is_sent_again(live_server, browser):
    page = browser.new_page()
    # a document of the app's origin without a page's CSP (which refuses the test's inline script); /static has no HTML
    page.goto(live_server.url + "/static/css/participant.css")
    page.add_script_tag(content=FAKE_SOCKET)
    page.evaluate("""async (hello) => {
        const { Teleop } = await import('/static/js/teleop.js');
        const noop = () => {};
        window.teleop = new Teleop({ url: 'ws://fake', onSetup: noop, onWorld: noop, onOver: noop, onGone: noop,
                                     onConnection: noop, onError: (e) => window.errors = [...(window.errors || []), e],
                                     log: noop });
        window.teleop.start('trial-1');
        await new Promise((r) => setTimeout(r, 10));
        window.socket.serve(hello);
        window.teleop.press('x+', 'KeyW');
        window.teleop.toggleGripper();
    }""", HELLO)
    inputs = page.evaluate("window.sent.filter((m) => m.type === 'input')")
    assert inputs[0]["ee_velocity"][0] > 0 and inputs[-1]["gripper"] == "close"
    last = inputs[-1]
    page.evaluate("(seq) => window.socket.serve({type: 'ack', seq, ok: false, error: 'too many messages; slow down'})",
                  last["seq"])
    page.wait_for_function(f"window.sent.filter((m) => m.type === 'input').length > {len(inputs):d}")
    again = page.evaluate("window.sent.filter((m) => m.type === 'input')")[-1]
    assert again["seq"] > last["seq"]
    assert (again["ee_velocity"], again["gripper"]) == (last["ee_velocity"], "close")
    assert page.evaluate("window.errors || []") == []  # a refusal the page repairs itself is not shown as an error

    # A refused keep-alive (or an older input) leaves the held state alone: nothing is sent again.
    count = len(page.evaluate("window.sent"))
    page.evaluate("(seq) => window.socket.serve({type: 'ack', seq, ok: false, error: 'too many messages; slow down'})",
                  again["seq"] - 1)
    page.wait_for_timeout(300)
    assert [m["type"] for m in page.evaluate("window.sent")[count:]] in ([], ["keepalive"], ["keepalive"] * 2)
