"""Screenshot a page in headless Chromium once ``document.title == "loaded"`` (+ settle time), over the DevTools
protocol with ``websockets`` only. ``python benchmarks/cdp_shot.py URL OUT.png [WIDTH HEIGHT SETTLE_S]``."""

from __future__ import annotations

import asyncio
import base64
import json
import re
import subprocess
import sys
import tempfile
import time
import urllib.request

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--no-first-run", "--disable-background-networking", "--disable-sync", "--hide-scrollbars"]


async def shot(url: str, out: str, width: int = 640, height: int = 640, settle: float = 5.0, timeout: float = 240):
    import websockets

    prof = tempfile.mkdtemp()
    proc = subprocess.Popen(["chromium", *FLAGS, f"--user-data-dir={prof}", f"--window-size={width},{height}",
                             "--remote-debugging-port=0", "about:blank"], stderr=subprocess.PIPE, text=True)
    try:
        port = None
        while port is None:
            m = re.search(r"DevTools listening on ws://127.0.0.1:(\d+)", proc.stderr.readline())
            port = m and m.group(1)
        pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list").read())
        ws_url = next(p["webSocketDebuggerUrl"] for p in pages if p["type"] == "page")
        async with websockets.connect(ws_url, max_size=2**28) as ws:
            n = 0

            async def call(method, **params):
                nonlocal n
                n += 1
                await ws.send(json.dumps({"id": n, "method": method, "params": params}))
                while True:
                    msg = json.loads(await ws.recv())
                    if msg.get("id") == n:
                        return msg.get("result", {})

            await call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                       mobile=False)
            await call("Page.navigate", url=url)
            t0 = time.time()
            while time.time() - t0 < timeout:
                r = await call("Runtime.evaluate", expression="document.title")
                if r.get("result", {}).get("value") == "loaded":
                    break
                await asyncio.sleep(0.5)
            loaded = time.time() - t0
            await asyncio.sleep(settle)
            data = (await call("Page.captureScreenshot", format="png"))["data"]
            open(out, "wb").write(base64.b64decode(data))
            print(f"loaded after {loaded:.1f} s; wrote {out}")
    finally:
        proc.kill()


if __name__ == "__main__":
    a = sys.argv[1:]
    asyncio.run(shot(a[0], a[1], *(int(x) for x in a[2:4]), *(float(x) for x in a[4:5])))
