"""Headless Chromium driven through the DevTools protocol (websocket-client, no browser download, no Playwright):
the browser tests, the viewer's cost benchmark and the README's screenshot open the viewer with it.

Needs Debian's `chromium` (apt-get install chromium) and `websocket-client` (the `test` extra).
"""

from __future__ import annotations

import base64
import itertools
import json
import shutil
import socket
import subprocess
import time
import urllib.request
from pathlib import Path
from typing import Any, Callable, Dict, Optional

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--remote-debugging-port=0",
]
"""Headless, offline, and with DevTools on a port Chromium picks (it writes it to <profile>/DevToolsActivePort)."""
ELEMENT_BY_LABEL = """(label) => {
    const element = [...document.querySelectorAll('label')].find(l => l.textContent.trim() === label);
    if (!element) return null;
    return document.getElementById(element.htmlFor) || element.closest('.mantine-Flex-root');
}"""
"""The GUI element viser labels with `label`: the label's target, else the label's row."""
INPUT_BY_LABEL = f"""(label) => {{
    const element = ({ELEMENT_BY_LABEL})(label);
    if (!element) return null;
    return element.tagName === 'INPUT' ? element : element.querySelector('input');
}}"""
"""The input of the GUI element labelled `label` (a slider's is hidden and holds its value)."""
ARROW_KEYS = {-1: ("ArrowLeft", 37), 1: ("ArrowRight", 39)}
"""DevTools key events that move a focused slider down and up."""


class DevTools:
    """Chromium driven through the DevTools protocol over its websocket (no browser download, no Playwright)."""

    def __init__(self, profile: Path, window_size: str = "1200,800") -> None:
        import websocket  # the test extra's; imported here so the package imports without it

        self.process = subprocess.Popen(
            [CHROMIUM, *CHROMIUM_FLAGS, f"--window-size={window_size}", f"--user-data-dir={profile}", "about:blank"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        port = self._devtools_port(profile / "DevToolsActivePort")
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
        page = next(target for target in pages if target["type"] == "page")
        self.socket = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=60, suppress_origin=True)
        self.ids = itertools.count(1)

    def _devtools_port(self, port_file: Path) -> int:
        deadline = time.monotonic() + 30
        while not (port_file.exists() and port_file.read_text().strip()):
            assert self.process.poll() is None, f"{CHROMIUM} exited with {self.process.returncode}"
            assert time.monotonic() < deadline, f"{CHROMIUM} did not open its DevTools port"
            time.sleep(0.1)
        return int(port_file.read_text().split()[0])

    def call(self, method: str, **params: Any) -> Dict[str, Any]:
        number = next(self.ids)
        self.socket.send(json.dumps({"id": number, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv())
            if message.get("id") == number:
                assert "error" not in message, f"{method}: {message['error']}"
                return message["result"]

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        assert "exceptionDetails" not in result, result["exceptionDetails"]
        return result["result"].get("value")

    def input_value(self, label: str) -> Optional[str]:
        return self.evaluate(f"(() => {{ const i = ({INPUT_BY_LABEL})({json.dumps(label)}); return i && i.value; }})()")

    def input_checked(self, label: str) -> bool:
        return self.evaluate(f"({INPUT_BY_LABEL})({json.dumps(label)}).checked")

    def input_disabled(self, label: str) -> bool:
        return self.evaluate(f"({INPUT_BY_LABEL})({json.dumps(label)}).disabled")

    def click_input(self, label: str) -> None:
        assert self.evaluate(f"(() => {{ ({INPUT_BY_LABEL})({json.dumps(label)}).click(); return true; }})()")

    def set_slider(self, label: str, value: float) -> None:
        """Move the slider labelled `label` to `value` as a user does with the keyboard: focus its thumb, press arrows."""
        thumb = f"({ELEMENT_BY_LABEL})({json.dumps(label)}).querySelector('[role=slider]')"
        read = f"(() => {{ const t = {thumb}; t.focus(); return Number(t.getAttribute('aria-valuenow')); }})()"
        for _ in range(100):
            current = self.evaluate(read)
            if current == value:
                return
            key, code = ARROW_KEYS[1 if value > current else -1]
            for event in ("keyDown", "keyUp"):
                self.call("Input.dispatchKeyEvent", type=event, key=key, code=key, windowsVirtualKeyCode=code)
        raise RuntimeError(f"the slider {label!r} did not reach {value}")

    def click_button(self, text: str) -> None:
        find = f"[...document.querySelectorAll('button')].find(b => b.textContent.trim() === {json.dumps(text)})"
        clicked = self.evaluate(f"(() => {{ const b = {find}; if (b) b.click(); return !!b; }})()")
        assert clicked, f"no button {text!r} on the page"

    def page_text(self) -> str:
        return self.evaluate("document.body ? document.body.innerText : ''")

    def screenshot_png(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def screenshot(self, path: Path) -> None:
        path.write_bytes(self.screenshot_png())

    def images(self) -> Dict[str, str]:
        """The page's images by their alt text: their sources (the panel's pictures are data URLs)."""
        return self.evaluate("Object.fromEntries([...document.querySelectorAll('img')].map(i => [i.alt, i.src]))")

    def image_width(self, alt: str) -> Optional[int]:
        """CSS pixels the page shows the image with alt text `alt` across, or None without such an image."""
        find = f"[...document.querySelectorAll('img')].find(i => i.alt === {json.dumps(alt)})"
        return self.evaluate(f"(() => {{ const i = {find}; return i ? i.clientWidth : null; }})()")

    def text_cut_off(self, start: str) -> bool:
        """Whether the innermost element whose text starts with `start` is wider than the room it is shown in."""
        find = f"[...document.querySelectorAll('body *')].reverse().find(e => e.textContent.trim().startsWith({json.dumps(start)}))"
        cut = f"(() => {{ const e = {find}; if (!e) return null; return e.scrollWidth > e.clientWidth; }})()"
        result = self.evaluate(cut)
        assert result is not None, f"no text starting with {start!r} on the page"
        return result

    def button_disabled(self, text: str) -> bool:
        find = f"[...document.querySelectorAll('button')].find(b => b.textContent.trim() === {json.dumps(text)})"
        return self.evaluate(f"(() => {{ const b = {find}; return !!b && b.disabled; }})()")

    def navigate(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def close(self) -> None:
        self.socket.close()
        self.process.terminate()
        self.process.wait(timeout=30)


def wait_for(
    what: str, condition: Callable[[], Any], timeout: float = 240.0, seen: Optional[Callable[[], Any]] = None
) -> None:
    """Poll `condition` until it holds; a hang detector, not a speed check: the timeout is generous because a busy
    shared 2-core machine renders several times slower than a quiet one. `seen` says what the page shows instead,
    for the message of a wait that timed out."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() >= deadline:
            shown = "" if seen is None else f"; last seen: {seen()!r}"
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}{shown}")
        time.sleep(0.2)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def viewer_answers(port: int) -> bool:
    """Whether a viewer serves its page on 127.0.0.1:`port`."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}", timeout=2) as response:
            return response.status == 200
    except OSError:
        return False
