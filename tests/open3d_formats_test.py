#!/usr/bin/python3
"""Prism's PLY, PCD and Draco files in Open3D (Debian's python3-open3d), and Open3D's files in Prism;
the COLMAP export's cameras put the ground-truth cloud onto the object in every image.

  open3d_formats_test.py BUILD_DIR
Skips when open3d is not importable.
"""
import json
import os
import shutil
import subprocess
import sys
import tempfile
import unittest

import numpy as np

try:
    import open3d as o3d
except ImportError:  # python3-open3d is optional (scripts/setup.sh does not install it)
    o3d = None

BUILD_DIR = None


def run(*args):
    r = subprocess.run([os.path.join(BUILD_DIR, "bin", args[0]), *args[1:]], capture_output=True, text=True)
    if r.returncode != 0:
        raise AssertionError(f"{' '.join(args)}: exit {r.returncode}: {r.stdout}{r.stderr}")
    return r.stdout


@unittest.skipIf(o3d is None, "python3-open3d is not installed")
class Open3dFormatsTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="prism_open3d_formats_test_")
        run("prism-synth", "--preset", "bunny-multicolor-forward", "--frames", "3", "--size", "160x120", "--out",
            os.path.join(cls.tmp, "seq"), "--gt-cloud", os.path.join(cls.tmp, "gt.ply"))

    def p(self, name):
        return os.path.join(self.tmp, name)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp)

    def assert_same(self, a, b, position_tolerance=0.0):
        self.assertEqual(len(a.points), len(b.points))
        self.assertGreater(len(a.points), 1000)
        # Open3D holds doubles; Prism's files hold floats (ASCII with 9 digits, which restores a float).
        np.testing.assert_allclose(np.asarray(a.points).astype(np.float32), np.asarray(b.points).astype(np.float32),
                                   rtol=0, atol=position_tolerance)
        self.assertTrue(a.has_normals() and b.has_normals())
        np.testing.assert_allclose(np.asarray(a.normals), np.asarray(b.normals), rtol=0, atol=1e-6)
        self.assertTrue(a.has_colors() and b.has_colors())
        # Open3D keeps colours as float in [0, 1]: the same 8-bit values.
        np.testing.assert_array_equal(np.round(np.asarray(a.colors) * 255), np.round(np.asarray(b.colors) * 255))

    def test_open3d_reads_prism_ply_pcd_and_draco(self):
        p = self.p
        run("prism-convert", "cloud", p("gt.ply"), p("b.pcd"))
        run("prism-convert", "cloud", p("gt.ply"), p("a.pcd"), "--ascii")
        run("prism-convert", "cloud", p("gt.ply"), p("c.drc"), "--draco-bits", "0")
        run("prism-convert", "cloud", p("c.drc"), p("from_drc.ply"))
        reference = o3d.io.read_point_cloud(p("gt.ply"))
        colors = np.round(np.asarray(reference.colors) * 255)
        self.assertGreater(len(np.unique(colors, axis=0)), 10)  # real colours, not a constant
        for name in ("b.pcd", "a.pcd", "from_drc.ply"):
            with self.subTest(file=name):
                self.assert_same(reference, o3d.io.read_point_cloud(p(name)))

    def test_prism_reads_open3d_files(self):
        p = self.p
        reference = o3d.io.read_point_cloud(p("gt.ply"))
        o3d.io.write_point_cloud(p("o3d_b.pcd"), reference, write_ascii=False)
        o3d.io.write_point_cloud(p("o3d_a.pcd"), reference, write_ascii=True)
        o3d.io.write_point_cloud(p("o3d.ply"), reference, write_ascii=False)
        for name in ("o3d_b.pcd", "o3d_a.pcd", "o3d.ply"):
            with self.subTest(file=name):
                out = json.loads(run("prism-convert", "cloud", p(name), p(name + ".back.ply")))
                self.assertTrue(out["normals"] and out["colors"], out)
                # Open3D's ASCII PCD has limited digits.
                self.assert_same(reference, o3d.io.read_point_cloud(p(name + ".back.ply")),
                                 position_tolerance=1e-6 if "_a" in name else 0.0)

    def test_colmap_cameras_project_the_object_onto_its_mask(self):
        p = self.p
        run("prism-convert", "colmap", "--trajectory", p("seq/groundtruth.txt"), "--camera", p("seq/camera.yaml"),
            "--sequence", p("seq"), "--map", p("gt.ply"), "--max-points", "100000", "--out", p("colmap"))
        cams = [line.split() for line in open(p("colmap/cameras.txt")) if not line.startswith("#")]
        self.assertEqual(len(cams), 1)
        _, model, width, height, fx, fy, cx, cy = cams[0]
        self.assertEqual(model, "PINHOLE")
        width, height, fx, fy, cx, cy = int(width), int(height), float(fx), float(fy), float(cx), float(cy)
        points = np.array([[float(v) for v in line.split()[1:4]] for line in open(p("colmap/points3D.txt"))
                           if not line.startswith("#")])
        # The cloud is the object and the ground plane z = 0 under it: keep the object (above 1 cm).
        points = points[points[:, 2] > 0.01]
        self.assertGreater(len(points), 500)
        lines = [line for line in open(p("colmap/images.txt")) if not line.startswith("#")]
        images = [line.split() for line in lines[::2]]
        self.assertEqual(len(images), 3)
        mask_by_rgb = {}
        for rgb_line, mask_line in zip(open(p("seq/rgb.txt")), open(p("seq/mask.txt"))):
            if not rgb_line.startswith("#"):
                mask_by_rgb[rgb_line.split()[1]] = mask_line.split()[1]
        for image in images:
            qw, qx, qy, qz, tx, ty, tz = map(float, image[1:8])
            name = image[9]
            self.assertTrue(os.path.exists(os.path.join(p("seq"), name)), name)
            rotation = o3d.geometry.get_rotation_matrix_from_quaternion([qw, qx, qy, qz])
            in_camera = points @ rotation.T + np.array([tx, ty, tz])
            self.assertTrue(np.all(in_camera[:, 2] > 0))
            # COLMAP's convention: the top-left pixel's centre is (0.5, 0.5), so pixel = floor(u, v).
            u = fx * in_camera[:, 0] / in_camera[:, 2] + cx
            v = fy * in_camera[:, 1] / in_camera[:, 2] + cy
            inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
            self.assertGreater(inside.mean(), 0.9)
            mask = np.asarray(o3d.io.read_image(os.path.join(p("seq"), mask_by_rgb[name])))
            on_object = mask[np.floor(v[inside]).astype(int), np.floor(u[inside]).astype(int)] == 255
            # Every object point projects into the object's silhouette (occluded ones too); edge pixels
            # may miss by a fraction of a pixel.
            min_fraction_on_object_mask = 0.97
            print(f"{name}: {on_object.mean():.4f} of {inside.sum()} object points on the object mask", file=sys.stderr)
            self.assertGreater(on_object.mean(), min_fraction_on_object_mask, name)


if __name__ == "__main__":
    BUILD_DIR = sys.argv[1]
    unittest.main(argv=sys.argv[:1], verbosity=2)
