#!/usr/bin/env python3
"""A hostile campaign against import, clips and what a run writes, from outside, as a user could
type it: mutated nerfstudio and COLMAP captures (transforms.json and images.txt values, BVH
numbers and lines, truncated or swapped photos and masks, hostile --units, --up, --max-size,
--masks and --out), clips given to `render --motion` and `export-avatar --motion`, and hostile
flags on render, relight and the exports (--orbit, --size, --intensity, --ground-height, --out
naming a user's folder or file). Counted as fuzz/hostile.py counts (panic, hang, silent, lost),
and a fourth kind of finding for an accepted import whose scene cannot be right:

- wrong: exit 0 with a scene whose body is not 0.25-10 m across, or a GLB holding a NaN.

Usage: python3 fuzz/hostile_capture.py --umbra target/debug/umbra --cases 300 [--seed 1]
"""

import argparse
import json
import math
import os
import random
import shutil
import struct
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from hostile import Campaign  # noqa: E402

HOSTILE_NUMBERS = ["0", "-1", "1e30", "-1e30", "nan", "inf", "1e300", "1e-12", "0.5", "128.5", "-3", "abc", ""]


class CaptureCampaign(Campaign):
    def __init__(self, umbra, work, seed):
        super().__init__(umbra, work, seed)
        self.counts["wrong"] = 0

    def make_bases(self):
        self.capture = os.path.join(self.work, "base-capture")
        self.check([self.umbra, "synth", "--out", self.capture, "--export", "nerfstudio", "--size", "32", "--cameras", "3", "--frames", "3", "--test-frames", "1"])
        self.scene = os.path.join(self.work, "base-scene")
        self.check([self.umbra, "synth", "--out", self.scene, "--size", "24", "--cameras", "3", "--frames", "2", "--test-frames", "1"])
        self.run_dir = os.path.join(self.work, "base-run")
        self.check([self.umbra, "fit", self.scene, "--out", self.run_dir, "--iterations", "2", "--no-eval"])
        self.colmap = os.path.join(self.work, "base-colmap")
        self.make_colmap(self.colmap)
        self.clip = open(os.path.join(self.capture, "motion.bvh")).read()

    def check(self, args):
        subprocess.run(args, check=True, capture_output=True)

    def make_colmap(self, out):
        """The capture's training images as a COLMAP text model, one camera per image."""
        doc = json.load(open(os.path.join(self.capture, "transforms.json")))
        os.makedirs(os.path.join(out, "sparse", "0"), exist_ok=True)
        shutil.copy(os.path.join(self.capture, "motion.bvh"), out)
        cameras, images = [], []
        train = set(doc["train_filenames"])
        for k, frame in enumerate(f for f in doc["frames"] if f["file_path"] in train):
            cameras.append(f"{k + 1} PINHOLE {frame['w']} {frame['h']} {frame['fl_x']} {frame['fl_y']} {frame['cx']} {frame['cy']}")
            m = frame["transform_matrix"]
            # OpenGL camera-to-world to OpenCV world-to-camera.
            r = [[m[i][0], -m[i][1], -m[i][2]] for i in range(3)]
            t = [m[i][3] for i in range(3)]
            rt = [[r[j][i] for j in range(3)] for i in range(3)]
            tt = [-sum(rt[i][j] * t[j] for j in range(3)) for i in range(3)]
            qw = math.sqrt(max(0.0, 1 + rt[0][0] + rt[1][1] + rt[2][2])) / 2
            qx = (rt[2][1] - rt[1][2]) / (4 * qw)
            qy = (rt[0][2] - rt[2][0]) / (4 * qw)
            qz = (rt[1][0] - rt[0][1]) / (4 * qw)
            name = f"cam{k:02}/{round(frame['time'] * 30):06}.png"
            images.append(f"{k + 1} {qw} {qx} {qy} {qz} {tt[0]} {tt[1]} {tt[2]} {k + 1} {name}")
            images.append("")
            for sub, key in (("images", "file_path"), ("masks", "mask_path")):
                target = os.path.join(out, sub, name)
                os.makedirs(os.path.dirname(target), exist_ok=True)
                shutil.copy(os.path.join(self.capture, frame[key]), target)
        open(os.path.join(out, "sparse", "0", "cameras.txt"), "w").write("\n".join(cameras) + "\n")
        open(os.path.join(out, "sparse", "0", "images.txt"), "w").write("\n".join(images) + "\n")

    # ----- checks of what an accepted command wrote -------------------------------------------

    def body_size(self, scene):
        """The diagonal of the first frame's bone heads' box (m)."""
        doc = json.load(open(os.path.join(scene, "scene.json")))
        heads = [(m[0][3], m[1][3], m[2][3]) for m in doc["frames"][0]["bone_to_world"]]
        return math.dist([min(h[i] for h in heads) for i in range(3)], [max(h[i] for h in heads) for i in range(3)])

    def imported_wrong(self, scene, label):
        try:
            size = self.body_size(scene)
        except (OSError, ValueError, KeyError, IndexError):
            size = float("nan")
        if not 0.2 <= size <= 12.0:
            self.counts["wrong"] += 1
            self.findings.append(("wrong", label, f"body {size} m"))

    def glb_wrong(self, path, label):
        data = open(path, "rb").read()
        json_length = struct.unpack("<I", data[12:16])[0]
        binary = data[20 + json_length + 8:]
        floats = struct.unpack(f"<{len(binary) // 4}f", binary[: len(binary) // 4 * 4])
        if any(not math.isfinite(f) for f in floats):
            self.counts["wrong"] += 1
            self.findings.append(("wrong", label, "a GLB with non-finite floats"))

    # ----- imports ----------------------------------------------------------------------------

    def mutate_text_numbers(self, text, count):
        """Replaces `count` numbers of `text` with hostile ones; returns the text."""
        words = text.split(" ")
        numeric = [i for i, w in enumerate(words) if w.strip().replace(".", "", 1).replace("-", "", 1).replace("e", "", 1).isdigit()]
        for _ in range(count):
            if not numeric:
                break
            i = self.rng.choice(numeric)
            tail = words[i][len(words[i].rstrip()):]
            words[i] = self.rng.choice(HOSTILE_NUMBERS) + tail
        return " ".join(words)

    def rewrite(self, path, change):
        """Replaces the text of `path` by `change(text)` (read before the file is opened to write)."""
        text = open(path).read()
        with open(path, "w") as f:
            f.write(change(text))

    def mutate_lines(self, text):
        lines = text.split("\n")
        how = self.rng.choice(["delete", "duplicate", "swap", "truncate"])
        i = self.rng.randrange(len(lines))
        if how == "delete":
            del lines[i]
        elif how == "duplicate":
            lines.insert(i, lines[i])
        elif how == "swap":
            j = self.rng.randrange(len(lines))
            lines[i], lines[j] = lines[j], lines[i]
        else:
            return text[: self.rng.randrange(len(text))]
        return "\n".join(lines)

    def mutate_photo(self, folder):
        images = [os.path.join(b, n) for b, _, fs in os.walk(folder) for n in fs if n.endswith(".png") and "/masks" not in b and "/images" in b]
        target = self.rng.choice(images)
        data = open(target, "rb").read()
        how = self.rng.choice(["truncate", "garbage", "empty", "mask-missing"])
        if how == "truncate":
            open(target, "wb").write(data[: len(data) // 2])
        elif how == "garbage":
            open(target, "wb").write(bytes(self.rng.randrange(256) for _ in range(300)))
        elif how == "empty":
            open(target, "wb").close()
        else:
            masks = [os.path.join(b, n) for b, _, fs in os.walk(folder) for n in fs if "/masks" in b]
            os.remove(self.rng.choice(masks))
        return how

    def import_cases(self, count, colmap):
        base = self.colmap if colmap else self.capture
        for k in range(count):
            capture = os.path.join(self.work, f"import-{k}")
            shutil.rmtree(capture, ignore_errors=True)
            shutil.copytree(base, capture)
            camera_file = os.path.join(capture, "sparse", "0", "images.txt" if self.rng.random() < 0.6 else "cameras.txt") if colmap else os.path.join(capture, "transforms.json")
            # The first case is the capture as it is: it must import, or the campaign tests nothing.
            kind = "control" if k == 0 else self.rng.choice(["cameras-numbers", "cameras-lines", "motion-numbers", "motion-lines", "photo", "flags", "flags"])
            must_refuse = None
            args_extra = []
            motion = os.path.join(capture, "motion.bvh")
            if kind == "cameras-numbers":
                self.rewrite(camera_file, lambda t: self.mutate_text_numbers(t, self.rng.randint(1, 3)))
            elif kind == "cameras-lines":
                self.rewrite(camera_file, self.mutate_lines)
            elif kind == "motion-numbers":
                self.rewrite(motion, lambda t: self.mutate_text_numbers(t, self.rng.randint(1, 3)))
            elif kind == "motion-lines":
                self.rewrite(motion, self.mutate_lines)
            elif kind == "control":
                pass
            elif kind == "photo":
                kind += " " + self.mutate_photo(capture)
                must_refuse = True
            else:
                flag = self.rng.choice(["units", "up", "max-size", "masks"])
                if flag == "units":
                    units = self.rng.choice(["m", "mm"])
                    args_extra = ["--units", units]
                    must_refuse = True  # the capture is in centimetres
                elif flag == "up":
                    args_extra = ["--up", "+z"]
                    must_refuse = True  # the capture is Y-up
                elif flag == "max-size":
                    size = self.rng.choice(["0", "1", "8", "15", "-1", "abc", "18446744073709551616"])
                    args_extra = ["--max-size", size]
                    must_refuse = True
                else:
                    args_extra = ["--masks", os.path.join(self.work, "no-such-masks")]
                    must_refuse = True
                kind += " " + flag
            out = os.path.join(self.work, f"import-out-{k}")
            p = self.run(["import", capture, "--out", out, "--light", "sun"] + args_extra, self.work, must_refuse is True, [capture], f"import {'colmap' if colmap else 'nerfstudio'} {kind}")
            if kind == "control" and (p is None or p.returncode != 0):
                self.findings.append(("control refused", f"import {'colmap' if colmap else 'nerfstudio'}", p.stderr.decode(errors="replace")[-500:] if p else "hang"))
                self.counts["silent"] += 1
            if p is not None and p.returncode == 0:
                self.imported_wrong(out, f"import {kind} {args_extra}")
            elif os.path.exists(out):
                self.counts["lost"] += 1
                self.findings.append(("written", f"a refused import wrote {out}", kind))
            shutil.rmtree(capture, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)

    # ----- clips ------------------------------------------------------------------------------

    def clip_cases(self, count):
        run = self.fresh_run("clip-run")
        scene_clip = os.path.join(self.work, "scene-clip.bvh")
        # A clip of the run's own skeleton: the base scene's motion, made by an import round trip
        # is not at hand, so the capture's clip (another body, retargeted) is the seed.
        open(scene_clip, "w").write(self.clip)
        for k in range(count):
            text = self.clip
            how = "control" if k < 2 else self.rng.choice(["numbers", "lines", "zero-offsets", "far-root", "frame-time"])
            must_refuse = None
            if how == "control":
                pass
            elif how == "numbers":
                text = self.mutate_text_numbers(text, self.rng.randint(1, 4))
            elif how == "lines":
                text = self.mutate_lines(text)
            elif how == "zero-offsets":
                text = "\n".join(("\t" * (len(l) - len(l.lstrip("\t"))) + "OFFSET 0 0 0") if l.strip().startswith("OFFSET") else l for l in text.split("\n"))
                must_refuse = True
            elif how == "far-root":
                lines = text.rstrip("\n").split("\n")
                values = lines[-1].split()
                values[self.rng.randrange(3)] = self.rng.choice(["1e30", "-1e30", "1e20"])
                lines[-1] = " ".join(values)
                text = "\n".join(lines) + "\n"
                must_refuse = True
            else:
                text = "\n".join(("Frame Time: " + self.rng.choice(["1e300", "0", "-1", "nan", "100"])) if l.startswith("Frame Time:") else l for l in text.split("\n"))
                must_refuse = True
            clip = os.path.join(self.work, f"clip-{k}.bvh")
            open(clip, "w").write(text)
            if k == 0 or (k > 1 and self.rng.random() < 0.5):
                out = os.path.join(self.work, f"clip-out-{k}")
                size = [] if k == 0 else self.rng.choice([[], ["--size", "16x16"], ["--orbit", self.rng.choice(["1", "3", "1000000000", "3601"])]])
                must = must_refuse is True or (len(size) == 2 and size[1] in ("1000000000", "3601"))
                p = self.run(["render", run, "--motion", clip, "--out", out] + size, self.work, must, [self.capture], f"render --motion {how} {size}")
                if k == 0 and (p is None or p.returncode != 0):
                    self.findings.append(("control refused", "render --motion", p.stderr.decode(errors="replace")[-500:] if p else "hang"))
                    self.counts["silent"] += 1
                shutil.rmtree(out, ignore_errors=True)
            else:
                glb = os.path.join(self.work, f"clip-{k}.glb")
                p = self.run(["export-avatar", run, "--motion", clip, "--out", glb], self.work, must_refuse is True, [self.capture], f"export-avatar --motion {how}")
                if k == 1 and (p is None or p.returncode != 0):
                    self.findings.append(("control refused", "export-avatar --motion", p.stderr.decode(errors="replace")[-500:] if p else "hang"))
                    self.counts["silent"] += 1
                if p is not None and p.returncode == 0 and os.path.exists(glb):
                    self.glb_wrong(glb, f"export-avatar --motion {how}")
                if os.path.exists(glb):
                    os.remove(glb)
            os.remove(clip)
        shutil.rmtree(run, ignore_errors=True)

    # ----- flags on a run's outputs ------------------------------------------------------------

    def output_cases(self, count):
        run = self.fresh_run("outputs-run")
        users = os.path.join(self.work, "users")
        user_file = os.path.join(self.work, "users-notes.txt")
        for k in range(count):
            shutil.rmtree(users, ignore_errors=True)
            os.makedirs(users)
            for name in ("sheet.png", "animation.png", "f0000.png", "c00_f0000.png", "notes.txt"):
                open(os.path.join(users, name), "w").write("mine")
            open(user_file, "w").write("comment umbra export-gaussians\n# umbra export-mesh\nmine")
            command = self.rng.choice(["relight", "render", "export-gaussians", "export-mesh", "export-avatar"])
            target = self.rng.choice(["users", "file", "fresh", "fresh", "dot"])
            out = {"users": users, "file": user_file, "fresh": os.path.join(self.work, f"fresh-{k}"), "dot": "."}[target]
            must_refuse = target in ("users", "file")
            cwd = users if target == "dot" else self.work
            if target == "dot":
                must_refuse = True  # the working folder holds a user's files
            flags = []
            if command in ("relight", "render"):
                choice = self.rng.choice(["orbit", "size", "intensity", "rotate", "ground", "camera", "frame", "none"])
                value = {
                    "orbit": self.rng.choice(["0", "1", "2", "3601", "1000000000", "18446744073709551615", "-1"]),
                    "size": self.rng.choice(["0x0", "8x8", "100000x1", "16x16", "axb", "9000x9000"]),
                    "intensity": self.rng.choice(["1e39", "-1", "nan", "inf", "2", "1e17"]),
                    "rotate": self.rng.choice(["nan", "inf", "720", "-45"]),
                    "ground": self.rng.choice(["nan", "inf", "1e30", "-1e30", "1000", "0"]),
                    "camera": self.rng.choice(["99", "-1", "0,0,0", "abc"]),
                    "frame": self.rng.choice(["99", "-1", "0,1"]),
                    "none": None,
                }[choice]
                flag = {"ground": "--ground-height"}.get(choice, "--" + choice)
                if value is not None:
                    flags = [flag, value]
                    bad = {
                        "orbit": value not in ("1", "2"),
                        "size": value not in ("8x8", "16x16"),
                        "intensity": value not in ("2", "1e17"),
                        "rotate": value in ("nan", "inf"),
                        "ground": value not in ("0",),
                        "camera": value not in ("0,0,0",),
                        "frame": value not in ("0,1",),
                    }[choice]
                    must_refuse = must_refuse or bad
                if choice == "orbit" and "--camera" in flags:
                    must_refuse = True
            if command == "relight":
                args = ["relight", run, "--light", "sun", "--out", out] + flags
            elif command == "render":
                args = ["render", run, "--out", out] + (flags or ["--camera", "0"])
            elif command == "export-gaussians":
                args = ["export-gaussians", run, "--frame", self.rng.choice(["0", "1", "99"]), "--out", out]
                must_refuse = must_refuse or args[3] == "99"
            elif command == "export-mesh":
                args = ["export-mesh", run, "--frame", "0", "--out", out]
            else:
                args = ["export-avatar", run, "--out", out]
            watched = [users] if target != "file" else [users]
            p = self.run(args, cwd, must_refuse, watched, f"{command} {target} {flags}")
            if not os.path.exists(user_file) or open(user_file).read() != "comment umbra export-gaussians\n# umbra export-mesh\nmine":
                self.counts["lost"] += 1
                self.findings.append(("lost", f"{command} {target}", args, [user_file]))
            fresh = os.path.join(self.work, f"fresh-{k}")
            if os.path.isdir(fresh):
                shutil.rmtree(fresh, ignore_errors=True)
            elif os.path.exists(fresh):
                os.remove(fresh)
            del p
        shutil.rmtree(run, ignore_errors=True)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--umbra", default="target/debug/umbra")
    parser.add_argument("--cases", type=int, default=300, help="cases of each kind: nerfstudio imports, COLMAP imports, clips, outputs")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--work")
    options = parser.parse_args()
    work = options.work or tempfile.mkdtemp(prefix="umbra-hostile-capture-")
    os.makedirs(work, exist_ok=True)
    campaign = CaptureCampaign(options.umbra, work, options.seed)
    campaign.make_bases()
    kinds = {}
    for name, cases in (("nerfstudio", lambda n: campaign.import_cases(n, False)), ("colmap", lambda n: campaign.import_cases(n, True)), ("clips", campaign.clip_cases), ("outputs", campaign.output_cases)):
        before = dict(campaign.counts)
        cases(options.cases)
        kinds[name] = {k: campaign.counts[k] - before[k] for k in campaign.counts}
    print(json.dumps({"total": campaign.counts, "by kind": kinds}, indent=1))
    for finding in campaign.findings:
        print(finding)
    shutil.rmtree(work, ignore_errors=True)
    return 1 if any(campaign.counts[k] for k in ("panic", "hang", "silent", "lost", "wrong")) else 0


if __name__ == "__main__":
    sys.exit(main())
