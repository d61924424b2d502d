#!/usr/bin/env python3
# The SLAM options table of docs/method.md: each key and default from `prism-slam --print-config`, its
# meaning from the comment on its field (scripts/report.sh slam-options).
import re
import subprocess
import sys
binary = sys.argv[1]
headers = {"": ("core/slam/slam_system.h", "SlamOptions"), "tracker": ("core/slam/tracker.h", "TrackerOptions"),
           "depth": ("core/slam/depth_filter.h", "DepthFilterOptions"),
           "keyframe_window_ba": ("core/slam/keyframe_ba.h", "DirectBaOptions"),
           "final_adjustment_ba": ("core/slam/keyframe_ba.h", "DirectBaOptions")}
def comment(path, struct, field):
    lines = open(path).read().split("\n")
    start = next(i for i, l in enumerate(lines) if re.match(rf"^struct {struct}\b", l))
    for i in range(start, len(lines)):
        if lines[i].startswith("};"):
            break
        if re.match(rf"^\s+[\w:<>]+ {field}( =|;|\{{)", lines[i]):
            text = []
            j = i - 1
            while j > start and lines[j].strip().startswith("//"):
                text.insert(0, lines[j].strip()[2:].strip())
                j -= 1
            trailing = lines[i].split("//", 1)
            if len(trailing) > 1:
                text.append(trailing[1].strip())
            return " ".join(text)
    return "?"
out = subprocess.run([binary, "--print-config"], capture_output=True, text=True, check=True).stdout
print("| key | default | meaning |")
print("|---|---|---|")
for line in out.splitlines():
    if not line or line.startswith("#"):
        continue
    key, value = [x.strip() for x in line.split("=", 1)]
    prefix, _, field = key.rpartition(".")
    path, struct = headers[prefix]
    print(f"| `{key}` | {value} | {comment(path, struct, field).replace('|', '/')} |")
