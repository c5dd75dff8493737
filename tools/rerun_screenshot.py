"""Screenshot of a Rerun recording in a headless Rerun viewer (the picture in docs/outputs.md).

::

    python tools/rerun_screenshot.py OUT/run.rrd docs/images/rerun_loop.jpg [--frame N]

Needs a graphics adapter; without a GPU, Mesa's software Vulkan driver
(``apt-get install mesa-vulkan-drivers``, "lavapipe") serves. The viewer shows the recording's
own default layout (``mslam.export.rerun_log``) at 1920x1080; the picture is saved at
1456x819 as JPEG.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd")
    ap.add_argument("out")
    ap.add_argument("--frame", type=int, help="time cursor (default: the last frame)")
    ap.add_argument("--port", type=int, default=9877)
    args = ap.parse_args()
    import rerun.experimental as rx

    viewer = rx.ViewerClient.spawn(headless=True, port=args.port, hide_welcome_screen=True)
    try:
        viewer.open(str(Path(args.rrd).resolve()))
        time.sleep(5)  # the viewer loads the file
        if args.frame is not None:
            viewer.set_time("frame", sequence=args.frame)
            time.sleep(2)
        with tempfile.TemporaryDirectory() as tmp:
            png = Path(tmp) / "shot.png"
            viewer.save_screenshot(str(png))
            img = cv2.imread(str(png))
    finally:
        viewer.quit()
    img = cv2.resize(img, (1456, 819), interpolation=cv2.INTER_AREA)
    cv2.imwrite(args.out, img, [cv2.IMWRITE_JPEG_QUALITY, 85])
    print(f"{args.out}: {img.shape[1]}x{img.shape[0]}")


if __name__ == "__main__":
    main()
