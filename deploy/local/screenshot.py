"""A screenshot of the operator's console, taken by Debian's chromium (headless)
through the Chrome DevTools Protocol: the launcher's --demo saves the finished
demo's console beside its report (console.png).

chromium's own --screenshot fires at the page's load event, before the
console has its data from the gateway; here the page is read until it shows
what `ready` (a JavaScript expression) asks for, then captured. The protocol's
messages go over python3-websocket (Debian's websocket-client).
"""

import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request

try:
    import websocket  # Debian's python3-websocket
except ImportError:  # the screenshot is skipped, with the reason
    websocket = None


def chromium_binary():
    return shutil.which("chromium") or shutil.which("chromium-browser")


class _Page:
    """One page target of a browser's DevTools endpoint."""

    def __init__(self, ws_url, timeout_s):
        self.socket = websocket.create_connection(ws_url, timeout=timeout_s,
                                                  suppress_origin=True)
        self.ids = itertools.count(1)

    def call(self, method, **params):
        message_id = next(self.ids)
        self.socket.send(json.dumps({"id": message_id, "method": method, "params": params}))
        while True:  # Events come in between; the reply has our id.
            reply = json.loads(self.socket.recv())
            if reply.get("id") == message_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error'].get('message')}")
                return reply.get("result", {})

    def close(self):
        self.socket.close()


def _devtools_port(profile, process, deadline):
    """The port chromium chose (--remote-debugging-port=0 writes it into the
    profile's DevToolsActivePort)."""
    path = os.path.join(profile, "DevToolsActivePort")
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"chromium exited with {process.returncode}")
        try:
            with open(path) as f:
                port = f.readline().strip()
            if port:
                return int(port)
        except OSError:
            pass
        time.sleep(0.05)
    raise RuntimeError("chromium did not open its DevTools port")


def take(url, path, ready="true", timeout_s=30.0, width=1280, height=1800):
    """Loads `url` in headless chromium, waits until `ready` is true in the
    page (at most timeout_s), and saves a PNG of the whole page to `path`.
    Returns None, or why there is no screenshot; says in the return value
    too when the page was captured before it was ready."""
    chromium = chromium_binary()
    if chromium is None:
        return "chromium is not installed (scripts/install-deps.sh installs it)"
    if websocket is None:
        return "python3-websocket is not installed (scripts/install-deps.sh installs it)"
    profile = tempfile.mkdtemp(prefix="behaviorlib-chromium-")
    process = subprocess.Popen(
        [chromium, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
         "--no-first-run", f"--window-size={width},{height}", "--remote-debugging-port=0",
         "--remote-debugging-address=127.0.0.1", f"--user-data-dir={profile}", url],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    page = None
    try:
        deadline = time.monotonic() + timeout_s
        port = _devtools_port(profile, process, deadline)
        target = None
        while target is None and time.monotonic() < deadline:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                targets = json.load(r)
            target = next((t for t in targets if t.get("type") == "page" and
                           t.get("url", "").startswith(url)), None)
            if target is None:
                time.sleep(0.1)
        if target is None:
            return f"chromium did not open {url}"
        page = _Page(target["webSocketDebuggerUrl"], timeout_s)
        is_ready = False
        while time.monotonic() < deadline:
            result = page.call("Runtime.evaluate", expression=ready, returnByValue=True)
            if result.get("result", {}).get("value") is True:
                is_ready = True
                break
            time.sleep(0.2)
        shot = page.call("Page.captureScreenshot", format="png", captureBeyondViewport=True)
        with open(path, "wb") as f:
            f.write(base64.b64decode(shot["data"]))
        return None if is_ready else f"captured before the page was ready ({ready})"
    except (OSError, RuntimeError, ValueError, websocket.WebSocketException) as error:
        return f"no screenshot: {error}"
    finally:
        if page is not None:
            page.close()
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        shutil.rmtree(profile, ignore_errors=True)
