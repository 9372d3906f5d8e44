#!/usr/bin/env python3
"""A hostile campaign against every umbra subcommand, from outside, as a user could type it.

Mutated scenes (scene.json values, the files it names: truncated, flipped, swapped for links,
FIFOs or folders), mutated runs and checkpoints (state.json with and without its checksum,
model and optimizer files damaged or removed), and hostile arguments (--out naming the working
folder, a user's folder or file). Every case runs with a time limit, its inputs snapshotted
before and after. Counts:

- panic: a Rust panic (exit 101 or "panicked" on stderr);
- hang: the time limit passed;
- silent: exit 0 where the case must be refused (a spec violation, an edited checkpoint without
  its checksum, an --out that is a user's file or folder);
- lost: a file that existed before the command (a user's) was removed or changed.

Usage: python3 fuzz/hostile.py --umbra target/debug/umbra --cases 400 [--seed 1] [--work DIR]
"""

import argparse
import hashlib
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile

TIME_LIMIT = 120


def snapshot(root):
    """Every file below root (links not followed) with a digest of its bytes."""
    out = {}
    for base, dirs, files in os.walk(root):
        for name in files + [d for d in dirs if os.path.islink(os.path.join(base, d))]:
            path = os.path.join(base, name)
            if os.path.islink(path):
                out[path] = "link:" + os.readlink(path)
            elif os.path.isfile(path):
                with open(path, "rb") as f:
                    out[path] = hashlib.sha256(f.read()).hexdigest()
            else:
                out[path] = "special"
    return out


def fnv1a(data):
    """The checksum umbra writes beside a checkpoint's state (scene::identity::file_checksum)."""
    h = 0xCBF29CE484222325
    for b in data:
        h = ((h ^ b) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return "%016x" % h


class Campaign:
    def __init__(self, umbra, work, seed):
        self.umbra = os.path.abspath(umbra)
        self.work = work
        self.rng = random.Random(seed)
        self.counts = {"cases": 0, "panic": 0, "hang": 0, "silent": 0, "lost": 0, "refused": 0, "accepted": 0}
        self.findings = []

    def run(self, args, cwd, must_refuse, watched, label):
        """Runs umbra with args in cwd; watched: folders whose files must survive."""
        before = {}
        for folder in watched:
            before.update(snapshot(folder))
        self.counts["cases"] += 1
        try:
            p = subprocess.run([self.umbra] + args, cwd=cwd, capture_output=True, timeout=TIME_LIMIT, stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            self.counts["hang"] += 1
            self.findings.append(("hang", label, args))
            return None
        err = p.stderr.decode(errors="replace")
        if p.returncode == 101 or "panicked" in err:
            self.counts["panic"] += 1
            self.findings.append(("panic", label, args, err[-2000:]))
        elif p.returncode == 0:
            self.counts["accepted"] += 1
            if must_refuse:
                self.counts["silent"] += 1
                self.findings.append(("silent", label, args))
        else:
            self.counts["refused"] += 1
        after = {}
        for folder in watched:
            after.update(snapshot(folder))
        lost = [path for path, digest in before.items() if after.get(path) != digest]
        if lost:
            self.counts["lost"] += len(lost)
            self.findings.append(("lost", label, args, lost[:5]))
        return p

    # ----- bases ------------------------------------------------------------------------------

    def make_bases(self):
        self.scene = os.path.join(self.work, "base-scene")
        subprocess.run([self.umbra, "synth", "--out", self.scene, "--size", "16", "--cameras", "2", "--frames", "2", "--test-frames", "1", "--meshes"], check=True, capture_output=True)
        self.run_dir = os.path.join(self.work, "base-run")
        subprocess.run([self.umbra, "fit", self.scene, "--out", self.run_dir, "--iterations", "2"], check=True, capture_output=True)

    def fresh_scene(self, name):
        path = os.path.join(self.work, name)
        shutil.rmtree(path, ignore_errors=True)
        shutil.copytree(self.scene, path, symlinks=True)
        return path

    def fresh_run(self, name):
        path = os.path.join(self.work, name)
        shutil.rmtree(path, ignore_errors=True)
        shutil.copytree(self.run_dir, path, symlinks=True)
        # The run names its scene absolutely: it stays the base scene.
        return path

    # ----- scene mutations --------------------------------------------------------------------

    HOSTILE_VALUES = [None, True, -1, 0, 1e308, -1e308, 1e40, 2**63, -(2**63), "NaN", "", "../../etc/passwd", "/dev/zero", [], {}, [[1, 2], [3]], "\u0000", 0.5]

    def mutate_value(self, doc):
        """Replaces one value somewhere in doc; returns whether the result must be refused
        (True), may be accepted (False) or is unknown (None)."""
        paths = []

        def walk(node, path):
            paths.append(path)
            if isinstance(node, dict):
                for k, v in node.items():
                    walk(v, path + [k])
            elif isinstance(node, list):
                for i, v in enumerate(node):
                    walk(v, path + [i])

        walk(doc, [])
        path = self.rng.choice(paths[1:])
        self.last_mutation = path
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        old = parent[path[-1]]
        action = self.rng.choice(["replace", "delete", "duplicate"])
        if action == "delete" and isinstance(parent, dict):
            del parent[path[-1]]
            # Optional keys: name, time, mesh, albedo, ambient, scale, generator, meshes.
            optional = {"name", "time", "mesh", "albedo", "ambient", "scale", "generator", "mask", "program", "version", "options"}
            return None if path[-1] in optional or "generator" in path else True
        if action == "duplicate" and isinstance(parent, list):
            parent.append(json.loads(json.dumps(old)))
            return None
        new = self.rng.choice(self.HOSTILE_VALUES)
        parent[path[-1]] = new
        if "generator" in path or path[-1] in ("name",):
            return None
        if new == old:
            return False
        return None

    def scene_cases(self, count):
        for k in range(count):
            scene = self.fresh_scene(f"scene-{k}")
            kind = self.rng.random()
            must_refuse = None
            with open(os.path.join(scene, "scene.json")) as f:
                doc = json.load(f)
            if kind < 0.55:
                for _ in range(self.rng.randint(1, 3)):
                    verdict = self.mutate_value(doc)
                    must_refuse = must_refuse or verdict
                with open(os.path.join(scene, "scene.json"), "w") as f:
                    json.dump(doc, f)
                label = "scene.json value"
            else:
                files = [i[key] for i in doc["images"] for key in ("path", "mask", "albedo") if key in i]
                files += [f["mesh"] for f in doc["frames"] if "mesh" in f]
                files += [l["path"] for l in doc["lights"].values() if "path" in l]
                target = os.path.join(scene, self.rng.choice(files))
                how = self.rng.choice(["truncate", "flip", "empty", "link-zero", "link-outside", "fifo", "folder", "garbage"])
                label = f"file {how}"
                must_refuse = how in ("truncate", "empty", "link-zero", "link-outside", "fifo", "folder", "garbage")
                data = open(target, "rb").read()
                os.remove(target)
                if how == "truncate":
                    open(target, "wb").write(data[: max(1, len(data) // 3)])
                elif how == "flip":
                    b = bytearray(data)
                    for _ in range(self.rng.randint(1, 8)):
                        i = self.rng.randrange(len(b))
                        b[i] ^= 1 << self.rng.randrange(8)
                    open(target, "wb").write(bytes(b))
                    must_refuse = None
                elif how == "empty":
                    open(target, "wb").close()
                elif how == "link-zero":
                    os.symlink("/dev/zero", target)
                elif how == "link-outside":
                    outside = os.path.join(self.work, f"outside-{k}")
                    open(outside, "wb").write(data)
                    os.symlink(outside, target)
                elif how == "fifo":
                    os.mkfifo(target)
                elif how == "folder":
                    os.mkdir(target)
                else:
                    open(target, "wb").write(bytes(self.rng.randrange(256) for _ in range(200)))
            command = self.rng.choice(["inspect", "fit"])
            args = ["inspect", scene] if command == "inspect" else ["fit", scene, "--out", os.path.join(self.work, f"scene-run-{k}"), "--iterations", "1", "--no-eval"]
            self.run(args, self.work, must_refuse is True, [scene], f"{label} {getattr(self, 'last_mutation', '')}")
            shutil.rmtree(os.path.join(self.work, f"scene-run-{k}"), ignore_errors=True)
            shutil.rmtree(scene, ignore_errors=True)

    # ----- run and checkpoint mutations -------------------------------------------------------

    def run_cases(self, count):
        for k in range(count):
            run = self.fresh_run(f"run-{k}")
            checkpoint = os.path.join(run, "checkpoint")
            state_path = os.path.join(checkpoint, "state.json")
            state = json.load(open(state_path))
            how = self.rng.choice(["state-edit", "state-edit-checksummed", "state-garbage", "file-flip", "file-remove", "file-truncate", "fit-json", "schedule"])
            must_refuse = how in ("state-edit", "state-garbage", "file-flip", "file-truncate")
            if how.startswith("state-edit"):
                for _ in range(self.rng.randint(1, 3)):
                    self.mutate_value(state)
                with open(state_path, "w") as f:
                    json.dump(state, f)
                if how == "state-edit-checksummed":
                    # A deliberate edit with its checksum recomputed: validation alone stands
                    # between it and a panic; refusing or rendering are both answers.
                    with open(os.path.join(checkpoint, "state.checksum"), "w") as f:
                        f.write(fnv1a(open(state_path, "rb").read()))
                    must_refuse = False
            elif how == "state-garbage":
                open(state_path, "wb").write(bytes(self.rng.randrange(256) for _ in range(300)))
            elif how.startswith("file-"):
                names = [n for n in os.listdir(checkpoint) if n.endswith(".bpk") or n == "state.checksum"]
                target = os.path.join(checkpoint, self.rng.choice(names))
                data = bytearray(open(target, "rb").read())
                if how == "file-remove":
                    os.remove(target)
                    must_refuse = True
                elif how == "file-truncate":
                    open(target, "wb").write(bytes(data[: len(data) // 2]))
                else:
                    i = self.rng.randrange(len(data))
                    data[i] ^= 0x10
                    open(target, "wb").write(bytes(data))
            elif how == "fit-json":
                report = os.path.join(run, "fit.json")
                doc = json.load(open(report))
                self.mutate_value(doc)
                json.dump(doc, open(report, "w"))
                must_refuse = False
            else:
                with open(os.path.join(run, "schedule.toml"), "a") as f:
                    f.write(self.rng.choice(["\niterations = -4\n", "\n[losses]\nmask = nan\n", "\x00\x01", "\nrays_per_batch = 1e12\n"]))
                must_refuse = True
            out = os.path.join(self.work, f"run-out-{k}")
            command = self.rng.choice(["render", "eval", "relight", "report", "export-mesh", "resume"])
            args = {
                "render": ["render", run],
                "eval": ["eval", run],
                "relight": ["relight", run, "--light", "sun", "--camera", "0", "--frame", "0", "--out", out],
                "report": ["report", run, "--directions", "16"],
                "export-mesh": ["export-mesh", run, "--frame", "0", "--out", out + ".obj"],
                "resume": ["fit", self.scene, "--out", run, "--iterations", "3", "--resume", "--no-eval"],
            }[command]
            # fit.json edits may break only the scene path: either answer is right.
            if how == "fit-json":
                must_refuse = False
            self.run(args, self.work, must_refuse, [self.scene], f"{how} / {command}")
            shutil.rmtree(run, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)
            if os.path.exists(out + ".obj"):
                os.remove(out + ".obj")

    # ----- hostile arguments ------------------------------------------------------------------

    def argument_cases(self):
        users = os.path.join(self.work, "users-folder")
        os.makedirs(os.path.join(users, "sub"), exist_ok=True)
        open(os.path.join(users, "notes.txt"), "w").write("mine")
        open(os.path.join(users, "sub", "c00_f0000.png"), "w").write("mine")
        user_file = os.path.join(self.work, "users-file.obj")
        open(user_file, "w").write("mine")
        run = self.fresh_run("args-run")
        cases = [
            (["synth", "--out", ".", "--force", "--size", "8", "--cameras", "1", "--frames", "1", "--test-frames", "1"], users),
            (["synth", "--out", "..", "--force", "--size", "8", "--cameras", "1", "--frames", "1", "--test-frames", "1"], os.path.join(users, "sub")),
            (["synth", "--out", users, "--force", "--size", "8", "--cameras", "1", "--frames", "1", "--test-frames", "1"], self.work),
            (["synth", "--out", user_file, "--force", "--size", "8", "--cameras", "1", "--frames", "1", "--test-frames", "1"], self.work),
            (["fit", self.scene, "--out", users, "--iterations", "1"], self.work),
            (["fit", self.scene, "--out", user_file, "--iterations", "1"], self.work),
            (["fit", self.scene, "--out", run, "--iterations", "99999999999"], self.work),
            (["fit", self.scene, "--out", run, "--resume", "--seed", "7", "--iterations", "3"], self.work),
            (["relight", run, "--light", "sun", "--out", os.path.join(users, "sub")], self.work),
            (["relight", run, "--light", "sun", "--out", user_file], self.work),
            (["export-mesh", run, "--frame", "0", "--out", user_file], self.work),
            # New files beside a user's (frame_PPPP.obj): allowed; none of theirs may change.
            (["export-mesh", run, "--all-frames", users], self.work, False),
            (["ablate", self.scene, "--schedule", "schedules/default.toml", "--schedule", "schedules/detail.toml", "--out", users, "--iterations", "1"], os.getcwd()),
            (["relight", run, "--light", "/dev/zero"], self.work),
            (["fit", self.scene, "--out", os.path.join(self.work, "x"), "--schedule", "/dev/zero"], self.work),
            (["inspect", "/dev/zero"], self.work),
            (["render", run, "--scene", "/dev/null"], self.work),
        ]
        for case in cases:
            args, cwd, must_refuse = case if len(case) == 3 else (*case, True)
            self.run(args, cwd, must_refuse, [users], "argument " + args[0])
            if not os.path.exists(user_file) or open(user_file).read() != "mine":
                self.counts["lost"] += 1
                self.findings.append(("lost", "argument " + args[0], args, [user_file]))
                open(user_file, "w").write("mine")


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--umbra", default="target/debug/umbra")
    parser.add_argument("--cases", type=int, default=300, help="mutated scenes and as many mutated runs")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--work")
    options = parser.parse_args()
    work = options.work or tempfile.mkdtemp(prefix="umbra-hostile-")
    os.makedirs(work, exist_ok=True)
    campaign = Campaign(options.umbra, work, options.seed)
    campaign.make_bases()
    campaign.argument_cases()
    campaign.scene_cases(options.cases)
    campaign.run_cases(options.cases)
    print(json.dumps(campaign.counts))
    for finding in campaign.findings:
        print(finding)
    shutil.rmtree(work, ignore_errors=True)
    return 1 if any(campaign.counts[k] for k in ("panic", "hang", "silent", "lost")) else 0


if __name__ == "__main__":
    sys.exit(main())
