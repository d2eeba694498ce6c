"""UI test: the add-on's render buttons in Blender with its full UI (not --background).

Run (needs a display; Xvfb gives one, Mesa renders the UI in software):

    xvfb-run -a -s "-screen 0 1600x1000x24" \
        blender --factory-startup --enable-event-simulate --python-exit-code 1 \
                --python clients/blender/tests/ui_test.py -- [--screenshot OUT.png]

tessera is taken from $TESSERA, else PATH, else this checkout's target/release/tessera.

The script runs before Blender's window loop starts, so it only registers the add-on
and a timer; all the work happens in timer steps (a generator, one step per timer call),
with operators called through `bpy.context.temp_override(window=, area=, region=)`.

Checks:
1. "Render on Tessera" as the button calls it (`INVOKE_DEFAULT`) returns
   {'RUNNING_MODAL'} with no image yet (the render runs while the UI keeps going),
   then "Tessera Render" appears, 160x120, within 60 s.
2. The animation button (`animation=True`, frames 1-3, a keyframed cube) ends with
   "Tessera Animation", an image sequence, within 60 s.
3. Esc during a farm render (a coordinator and a worker on 127.0.0.1, started here)
   cancels the job on the farm and ends in one report (needs --enable-event-simulate,
   which makes Blender take its events from the script only).
4. With --screenshot: the Properties editor's Render tab with the Tessera panel open,
   its fields filled in, saved as a PNG. `--no-render` skips 1 and 2 (only the picture).

Exit status 0 when all pass, 1 on any failure (printed as "ui test: FAIL: ..."); a
watchdog thread ends the run with status 1 after 120 s whatever Blender is doing.
"""

import os
import shutil
import signal
import struct
import sys
import tempfile
import threading
import time
import traceback

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
import tessera_blender  # noqa: E402

RENDER_TIMEOUT = 60.0
WATCHDOG = 120.0
STILL = "Tessera Render"
ANIM = "Tessera Animation"
T0 = time.monotonic()


def log(msg):
    print("ui test [%6.2fs]: %s" % (time.monotonic() - T0, msg), flush=True)


def addon_reports():
    """The add-on's reports so far, if it keeps a list of them (a modal operator's
    reports reach the status bar, not stdout)."""
    reps = getattr(getattr(tessera_blender, "ui", None), "REPORTS", None)
    return list(reps) if isinstance(reps, list) else []


def kill_children():
    """Ends the processes this Blender started (a local tessera render still running
    when the test gives up), so none outlives the test. Linux /proc; else nothing."""
    me = os.getpid()
    for pid in os.listdir("/proc") if os.path.isdir("/proc") else []:
        if not pid.isdigit():
            continue
        try:
            with open("/proc/%s/stat" % pid) as f:
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            if ppid == me:
                os.kill(int(pid), signal.SIGTERM)
        except (OSError, ValueError, IndexError):
            pass


def fail(msg):
    for level, text in addon_reports():
        print("ui test: add-on report %s: %s" % (level, text), flush=True)
    kill_children()
    print("ui test: FAIL: %s" % msg, flush=True)
    sys.stderr.flush()
    os._exit(1)


def args():
    a = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else []
    out = {"screenshot": None, "no_render": False}
    i = 0
    while i < len(a):
        if a[i] == "--screenshot" and i + 1 < len(a):
            out["screenshot"] = os.path.abspath(a[i + 1])
            i += 2
        elif a[i] == "--no-render":
            out["no_render"] = True
            i += 1
        else:
            fail("unknown argument %r (usage: -- [--screenshot OUT.png] [--no-render])" % a[i])
    return out


def tessera_exe():
    cand = os.environ.get("TESSERA") or shutil.which("tessera")
    if not cand:
        repo = os.path.dirname(os.path.dirname(os.path.dirname(HERE)))
        cand = os.path.join(repo, "target", "release", "tessera")
    cand = os.path.abspath(cand)
    if not os.access(cand, os.X_OK):
        fail("no tessera executable (set $TESSERA or put tessera on PATH): %s" % cand)
    return cand


def ui_context(kind="VIEW_3D"):
    """window, area and its main region of the first area of this type."""
    win = bpy.context.window_manager.windows[0]
    for area in win.screen.areas:
        if area.type == kind:
            region = next(r for r in area.regions if r.type == "WINDOW")
            return dict(window=win, area=area, region=region)
    fail("no %s area in the window" % kind)


def build_scene(exe):
    sc = bpy.context.scene
    sc.render.resolution_x, sc.render.resolution_y = 160, 120
    sc.render.resolution_percentage = 100
    for name in ("Cube", "Camera", "Light"):
        if name not in bpy.data.objects:
            fail("factory startup scene has no %r" % name)
    light = bpy.data.objects["Light"]
    if light.data.type != "POINT":
        light.data.type = "POINT"
    sc.camera = bpy.data.objects["Camera"]
    sc.tessera.address = ""
    sc.tessera.tessera_path = exe
    # the animation: the cube moves and turns over frames 1-3
    cube = bpy.data.objects["Cube"]
    sc.frame_start, sc.frame_end = 1, 3
    sc.frame_set(1)
    cube.location = (0, 0, 0)
    cube.rotation_euler = (0, 0, 0)
    cube.keyframe_insert("location", frame=1)
    cube.keyframe_insert("rotation_euler", frame=1)
    cube.location = (0.8, 0, 0.3)
    cube.rotation_euler = (0, 0, 0.6)
    cube.keyframe_insert("location", frame=3)
    cube.keyframe_insert("rotation_euler", frame=3)
    sc.frame_set(1)


def remove_image(name):
    img = bpy.data.images.get(name)
    if img is not None:
        bpy.data.images.remove(img)


def invoke_render(**kw):
    """Calls the operator as its button does; returns (result, seconds the call took)."""
    t = time.monotonic()
    with bpy.context.temp_override(**ui_context("VIEW_3D")):
        try:
            res = bpy.ops.render.tessera_render("INVOKE_DEFAULT", **kw)
        except TypeError as e:          # e.g. an operator property that does not exist
            fail("render.tessera_render(%s): %s" % (kw, e))
        except RuntimeError as e:       # the operator reported an error
            fail("render.tessera_render(%s) reported: %s" % (kw, e))
    return res, time.monotonic() - t


def operator_running():
    """True/False from the render operator's class flag, None if it has none."""
    cls = getattr(bpy.types, "TESSERA_OT_render", None) or getattr(
        getattr(tessera_blender, "ui", None), "TESSERA_OT_render", None)
    flag = getattr(cls, "_running", None)
    return flag if isinstance(flag, bool) else None


def wait_for(what, ready, timeout=RENDER_TIMEOUT):
    """Generator: yields poll intervals until ready() or timeout (then fails)."""
    t = time.monotonic()
    steps = 0
    ended = None
    while not ready():
        if time.monotonic() - t > timeout:
            fail("%s: not there after %.0f s" % (what, timeout))
        # Fail fast when the operator has ended without the image (its error report is
        # printed above). Uses the operator class's "a render is running" flag if it has one.
        if operator_running() is False:
            ended = ended or time.monotonic()
            if time.monotonic() - ended > 1.0:
                fail("%s: the render operator ended without it (its reports are listed above)" % what)
        steps += 1
        yield 0.1
    log("%s after %.2f s (%d polls meanwhile)" % (what, time.monotonic() - t, steps))


def test_still():
    remove_image(STILL)
    res, took = invoke_render()
    log("INVOKE_DEFAULT returned %s in %.3f s" % (sorted(res), took))
    # The image is loaded on the main thread (the operator's modal step), which cannot
    # run while this timer step runs: if it exists now, invoke rendered synchronously.
    if bpy.data.images.get(STILL) is not None:
        fail("%r exists right after the INVOKE call returned %s: the render blocked "
             "the UI (the operator must be modal)" % (STILL, sorted(res)))
    if res != {"RUNNING_MODAL"}:
        fail("INVOKE_DEFAULT returned %s, expected {'RUNNING_MODAL'}" % sorted(res))
    yield from wait_for("still image %r 160x120" % STILL, lambda: (
        bpy.data.images.get(STILL) is not None
        and tuple(bpy.data.images[STILL].size) == (160, 120)))
    img = bpy.data.images[STILL]
    px = img.pixels[:]
    if len(px) != 160 * 120 * 4:
        fail("%r has %d pixel values, not 160*120*4" % (STILL, len(px)))
    # a rendered cube on black: some pixels must be lit
    lit = sum(1 for i in range(0, len(px), 4) if px[i] + px[i + 1] + px[i + 2] > 0.05)
    log("still: %d of %d pixels lit" % (lit, len(px) // 4))
    if lit < 100:
        fail("%r is (nearly) black: %d lit pixels" % (STILL, lit))


def png_size(path):
    with open(path, "rb") as f:
        head = f.read(24)
    if head[:8] != b"\x89PNG\r\n\x1a\n":
        fail("%s is not a PNG" % path)
    return struct.unpack(">II", head[16:24])


def test_animation():
    remove_image(ANIM)
    # Frames go to the scene's output path, as Blender's own animation renders do.
    out = tempfile.mkdtemp(prefix="tessera-ui-test-")
    bpy.context.scene.render.filepath = os.path.join(out, "frame_")
    res, took = invoke_render(animation=True)
    log("INVOKE_DEFAULT animation=True returned %s in %.3f s" % (sorted(res), took))
    if bpy.data.images.get(ANIM) is not None:
        fail("%r exists right after the INVOKE call returned: not modal" % ANIM)
    if res != {"RUNNING_MODAL"}:
        fail("INVOKE_DEFAULT animation=True returned %s, expected {'RUNNING_MODAL'}" % sorted(res))
    yield from wait_for("image sequence %r" % ANIM, lambda: (
        bpy.data.images.get(ANIM) is not None
        and bpy.data.images[ANIM].source == "SEQUENCE"))
    img = bpy.data.images[ANIM]
    log("animation: %s %s, files %s" % (img.source, img.filepath, sorted(os.listdir(out))))
    for f in (1, 2, 3):
        path = os.path.join(out, "frame_%04d.png" % f)
        if not os.path.exists(path):
            fail("frame %d: no %s" % (f, path))
        if png_size(path) != (160, 120):
            fail("frame %d: %s is %s, not 160x120" % (f, path, png_size(path)))
    shutil.rmtree(out, ignore_errors=True)


def test_cancel(exe):
    """Esc while a farm render runs: the job is cancelled on the farm, and the
    operator ends with one report saying so. The key press is simulated
    (Blender started with --enable-event-simulate)."""
    sys.path.insert(0, HERE)
    from farm import TOKEN, Farm
    work = tempfile.mkdtemp(prefix="tessera-ui-cancel-")
    farm = Farm(exe, work)
    try:
        sc = bpy.context.scene
        sc.tessera.address, sc.tessera.token_file = farm.url, farm.token_file
        sc.render.resolution_x, sc.render.resolution_y = 1920, 1080
        sc.tessera.aa = 16            # minutes on one worker thread: Esc comes first
        del tessera_blender.ui.REPORTS[:]
        res, _ = invoke_render()
        if res != {"RUNNING_MODAL"}:
            fail("farm render: INVOKE_DEFAULT returned %s" % sorted(res))
        sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(HERE)), "python", "src"))
        from tessera_client import Client
        client = Client(farm.url, token=TOKEN, use_env=False)
        t = time.monotonic()
        while not [j for j in client.jobs() if j.state == "running"]:
            if time.monotonic() - t > 30:
                fail("the farm job did not start running")
            yield 0.1
        win = bpy.context.window_manager.windows[0]
        win.event_simulate(type="ESC", value="PRESS")
        win.event_simulate(type="ESC", value="RELEASE")
        t = time.monotonic()
        while operator_running() is not False:
            if time.monotonic() - t > 20:
                fail("Esc: the render operator is still running after 20 s")
            yield 0.1
        reports = tessera_blender.ui.REPORTS
        if len(reports) != 1 or reports[0][0] != "WARNING" or "cancelled on the farm" not in reports[0][1]:
            fail("Esc: expected one report saying cancelled, got %r" % (reports,))
        states = [j.state for j in client.jobs()]
        if states != ["cancelled"]:
            fail("Esc: the farm's jobs are %r, not one cancelled job" % states)
        if bpy.data.images.get(STILL) is not None and bpy.data.images[STILL].size[0] == 1920:
            fail("Esc: an image was loaded anyway")
        log("Esc cancelled the farm's job in %.2f s; report %r" % (time.monotonic() - t, reports[0][1]))
    finally:
        farm.stop()
        shutil.rmtree(work, ignore_errors=True)
        sc = bpy.context.scene
        sc.tessera.address = ""
        sc.render.resolution_x, sc.render.resolution_y = 160, 120


def screenshot_steps(out):
    wm = bpy.context.window_manager
    win = wm.windows[0]
    prefs = bpy.context.preferences
    prefs.view.ui_scale = 1.25           # readable when the picture is shown scaled down
    prefs.view.show_tooltips = False     # the pointer rests over the UI under Xvfb
    win.cursor_warp(10, 10)              # ... and away from the Properties editor
    yield 0.3
    # Split the big 3D view: its right part (about 900 px wide, the height of the
    # 3D view) becomes a Properties editor. (screen.area_move would be simpler, but
    # its poll fails when the pointer is over a region, as it is under Xvfb.)
    v3d = ui_context("VIEW_3D")
    big = v3d["area"]
    factor = 1.0 - 900.0 / big.width
    before = set(a.as_pointer() for a in win.screen.areas)
    with bpy.context.temp_override(**v3d):
        res = bpy.ops.screen.area_split(direction="VERTICAL", factor=factor)
    if res != {"FINISHED"}:
        fail("screen.area_split returned %s" % sorted(res))
    yield 0.2
    new = [a for a in win.screen.areas if a.as_pointer() not in before]
    area = new[0] if new else max((a for a in win.screen.areas if a.type == "VIEW_3D"),
                                  key=lambda a: a.x)
    if area.x < big.x + 10:      # the new area is the left one: use the right one
        area = max((a for a in win.screen.areas if a.type == "VIEW_3D"), key=lambda a: a.x)
    # Then its lower part, about 580 px tall, is the one pictured.
    ctx = dict(window=win, area=area, region=next(r for r in area.regions if r.type == "WINDOW"))
    before = set(a.as_pointer() for a in win.screen.areas)
    with bpy.context.temp_override(**ctx):
        res = bpy.ops.screen.area_split(direction="HORIZONTAL", factor=580.0 / area.height)
    if res != {"FINISHED"}:
        fail("screen.area_split returned %s" % sorted(res))
    yield 0.2
    pair = [area] + [a for a in win.screen.areas if a.as_pointer() not in before]
    area = min(pair, key=lambda a: a.y)
    area.type = "PROPERTIES"
    yield 0.2
    space = area.spaces.active
    space.context = "RENDER"
    sc = bpy.context.scene
    # Workbench has few render panels, so few are around the Tessera panel.
    sc.render.engine = "BLENDER_WORKBENCH"
    sc.tessera.address = "http://render-farm.local:7879"
    sc.tessera.token_file = "~/.config/tessera/client.token"
    sc.tessera.tls_fingerprint = ""
    sc.tessera.tessera_path = "tessera"
    sc.render.resolution_x, sc.render.resolution_y = 1280, 720
    sc.frame_start, sc.frame_end = 1, 120
    area.tag_redraw()
    yield 0.3
    # The add-on's panel comes after Blender's own render panels: scroll to the end.
    region = next(r for r in area.regions if r.type == "WINDOW")
    ctx = dict(window=win, area=area, region=region)
    with bpy.context.temp_override(**ctx):
        for _ in range(40):
            bpy.ops.view2d.scroll_down(deltay=400)
        bpy.ops.wm.redraw_timer(type="DRAW_WIN_SWAP", iterations=1)
    yield 0.3
    if "TESSERA_PT_render" not in dir(bpy.types):
        fail("panel TESSERA_PT_render is not registered")
    os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
    if os.path.exists(out):
        os.remove(out)
    with bpy.context.temp_override(**ctx):
        res = bpy.ops.screen.screenshot_area(filepath=out)
    if res != {"FINISHED"} or not os.path.exists(out):
        fail("screenshot_area returned %s, %s missing" % (sorted(res), out))
    log("screenshot %s (%d x %d area, %d bytes)" % (out, area.width, area.height,
                                                     os.path.getsize(out)))


def main(opts):
    log("UI up: %d window(s), areas %s" % (len(bpy.context.window_manager.windows),
                                           [a.type for a in bpy.context.window_manager.windows[0].screen.areas]))
    build_scene(tessera_exe())
    yield 0.1
    if not opts["no_render"]:
        yield from test_still()
        yield from test_animation()
        if bpy.app.use_event_simulate:
            yield from test_cancel(tessera_exe())
        else:
            log("Esc test skipped: Blender was not started with --enable-event-simulate")
    if opts["screenshot"]:
        yield from screenshot_steps(opts["screenshot"])
    log("all checks passed")


def start():
    opts = args()
    if bpy.app.background:
        # Timers never run in --background: the test would end at once and pass.
        fail("this test needs Blender's UI: run it under xvfb-run, without --background")
    # No splash screen: it would cover the screenshot. Read when the window loop starts.
    bpy.context.preferences.view.show_splash = False
    tessera_blender.register()
    steps = main(opts)

    def step():
        try:
            return next(steps)
        except StopIteration:
            print("ui test: ok", flush=True)
            sys.stderr.flush()
            os._exit(0)
        except SystemExit:
            raise
        except BaseException:
            traceback.print_exc()
            fail("exception in a timer step")

    def watchdog():
        fail("watchdog: the run took more than %.0f s" % WATCHDOG)

    # A thread, not a Blender timer: it fires even if a blocking operator holds the UI.
    t = threading.Timer(WATCHDOG, watchdog)
    t.daemon = True
    t.start()
    # persistent: survives loading the startup file after this script ran
    bpy.app.timers.register(step, first_interval=0.5, persistent=True)


start()
