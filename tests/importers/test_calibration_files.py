"""Other tools' camera calibration files: each real DAVIS346 file of tests/data read (its
numbers checked against the file's), each writer read back, and the errors a person meets."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from evcap.errors import InputError, InputNotFoundError, OutputExistsError
from evcap.importers.calibration_files import (
    CameraCalibration,
    check_size,
    export_format,
    read_calibration_file,
    write_calibration_file,
)

DATA = Path(__file__).resolve().parents[1] / "data" / "davis346-calibrations"
KALIBR_IMU = DATA / "arclab_esvio_kalibr_camchain-imucam.yaml"
# the camera-IMU transform of that camchain, as the file prints it
T_CAM_IMU = [
    [0.9999552277012158, -0.00603191153357543, 0.007290996931816412, 0.00011018857347815285],
    [0.005994670026470383, 0.9999689294906282, 0.005118982773930891, -0.0007730487905611042],
    [-0.007321647648062164, -0.005075046464534421, 0.9999603179022153, -0.060160984076249716],
    [0.0, 0.0, 0.0, 1.0],
]

# file, camera, format, (fx, fy, cx, cy), distortion model, coefficients: the files' numbers
REAL = [
    (
        "esvo_hkust_davis346_left.yaml",
        "hkust_DAVIS346_left",
        "ROS camera_info",
        (263.796, 263.738, 176.994, 124.373),
        "radtan",
        [-0.386589, 0.157241, 0.000322143, 6.13759e-06],
    ),
    (
        "esvo_hkust_davis346_right.yaml",
        "hkust_DAVIS346_right",
        "ROS camera_info",
        (263.485, 263.276, 162.942, 118.029),
        "radtan",
        [-0.383425, 0.152823, -0.000257745, 0.000268432],
    ),
    (
        "esvo_upenn_davis346_left.yaml",
        "upenn_DAVIS346_left",
        "ROS camera_info",
        (226.38018519795807, 226.15002947047415, 173.6470807871759, 133.73271487507847),
        "equidistant",
        [-0.048031442223833355, 0.011330957517194437, -0.055378166304281135, 0.021500973881459395],
    ),
    (
        "esvo_upenn_davis346_right.yaml",
        "upenn_DAVIS346_right",
        "ROS camera_info",
        (226.0181418548734, 225.7869434267677, 174.5433576736815, 124.21627572590607),
        "equidistant",
        [-0.04846669832871334, 0.010092844338123635, -0.04293073765014637, 0.005194706897326005],
    ),
    (
        "arclab_esvio_kalibr_camchain-imucam.yaml",
        "cam0",
        "Kalibr camchain",
        (248.7782253406866, 247.93713572288877, 176.4921016549297, 129.31466885208272),
        "radtan",
        [-0.3674645003666135, 0.13685246896794986, -0.0004006812242899775, 3.0969134907500055e-05],
    ),
    (
        "arclab_esvio_kalibr_stereo_camchain.yaml",
        "cam0",
        "Kalibr camchain",
        (249.69341447817564, 248.41625664694038, 176.74240257052816, 129.47631010746218),
        "radtan",
        [-0.3794794654640921, 0.15393049046270296, 0.0011400586965363895, -0.0019042695753031854],
    ),
    (
        "arclab_iros2022_davis346.yaml",
        "camera",
        "VINS",
        (259.355, 259.58, 177.005, 137.922),
        "radtan",
        [-0.373464, 0.139924, -0.000309077, 0.000635965],
    ),
    (
        "arclab_plevio_davis346.yaml",
        "camera",
        "VINS",
        (248.7782253406866, 247.93713572288877, 176.4921016549297, 129.31466885208272),
        "radtan",
        [-0.3674645003666135, 0.13685246896794986, -0.0004006812242899775, 3.0969134907500055e-05],
    ),
]
READABLE = [row[0] for row in REAL]


def fxy(cal: CameraCalibration) -> tuple[float, float, float, float]:
    K = cal.K
    return K[0, 0], K[1, 1], K[0, 2], K[1, 2]


@pytest.mark.parametrize(("name", "camera", "fmt", "intrinsics", "model", "dist"), REAL)
def test_each_real_davis346_calibration_reads(name, camera, fmt, intrinsics, model, dist):
    cal = read_calibration_file(DATA / name)
    assert (cal.width, cal.height) == (346, 260)
    assert cal.camera == camera and cal.format == fmt and cal.source == name
    assert fxy(cal) == intrinsics  # the file's numbers, exactly
    assert cal.skew == 0 and cal.K[1, 0] == 0 and list(cal.K[2]) == [0, 0, 1]
    assert cal.distortion_model == model and cal.dist.tolist() == dist
    check_size(cal, 346, 260, "a DAVIS346 session")


def test_kalibr_brings_the_camera_imu_transform_and_time_shift():
    cal = read_calibration_file(KALIBR_IMU)
    np.testing.assert_array_equal(cal.T_cam_imu, T_CAM_IMU)
    assert cal.timeshift_cam_imu_s == 0.0019438323735646128
    assert (
        read_calibration_file(DATA / "arclab_esvio_kalibr_stereo_camchain.yaml").T_cam_imu is None
    )
    assert read_calibration_file(DATA / "esvo_hkust_davis346_left.yaml").T_cam_imu is None


def test_vins_extrinsics_are_the_inverse_of_kalibrs():
    """VINS holds the camera's pose in the IMU's frame (imu_T_cam); PL-EVIO's file is the ESVIO
    camchain's camera, its extrinsics printed to 8 digits."""
    vins = read_calibration_file(DATA / "arclab_plevio_davis346.yaml")
    np.testing.assert_allclose(vins.T_cam_imu, T_CAM_IMU, atol=2e-8)
    assert vins.timeshift_cam_imu_s == 0.0  # no td in the file
    iros = read_calibration_file(DATA / "arclab_iros2022_davis346.yaml")
    R_imu_cam = [
        [0.99892148, -0.04476788, 0.01231717],
        [0.04454212, 0.99884479, 0.01803002],
        [-0.0131101, -0.01746194, 0.99976157],
    ]
    # to the file's 8 digits (its rotation is as orthonormal as that)
    np.testing.assert_allclose(iros.T_cam_imu[:3, :3], np.transpose(R_imu_cam), atol=1e-7)
    t_imu_cam = [0.00014722, -0.00025718, 0.00005513]
    t = -np.transpose(R_imu_cam) @ t_imu_cam
    np.testing.assert_allclose(iros.T_cam_imu[:3, 3], t, rtol=0, atol=1e-10)


def test_a_camera_matrix_with_a_stray_last_row_is_read_and_said():
    cal = read_calibration_file(DATA / "esvo_hkust_davis346_right.yaml")
    assert len(cal.warnings) == 1
    assert "[-0.0151344, 0.00133093, 0.999885]" in cal.warnings[0]


def test_a_stereo_camchain_gives_the_camera_asked_for():
    path = DATA / "arclab_esvio_kalibr_stereo_camchain.yaml"
    cam1 = read_calibration_file(path, "cam1")
    assert cam1.camera == "cam1" and cam1.cameras == ("cam0", "cam1")
    assert fxy(cam1) == (
        258.61441518089174,
        258.00363445501824,
        178.44356547141308,
        135.84792628403616,
    )
    assert "cam1 of cam0, cam1" in cam1.describe()
    assert read_calibration_file(path).camera == "cam0"  # the default
    with pytest.raises(InputError, match=r"no camera 'cam2': it holds 2 \(cam0, cam1\)"):
        read_calibration_file(path, "cam2")
    with pytest.raises(InputError, match=r"no camera 'cam1': it holds 1 \(hkust_DAVIS346_left\)"):
        read_calibration_file(DATA / "esvo_hkust_davis346_left.yaml", "cam1")
    # a single camera answers to its own name and to cam0
    left = DATA / "esvo_hkust_davis346_left.yaml"
    assert read_calibration_file(left, "hkust_DAVIS346_left").camera == "hkust_DAVIS346_left"
    assert read_calibration_file(left, "cam0").camera == "hkust_DAVIS346_left"


def test_an_imu_calibration_is_told_from_a_cameras():
    with pytest.raises(InputError, match="Kalibr IMU calibration.*no camera in it.*camchain"):
        read_calibration_file(DATA / "arclab_esvio_kalibr_imu.yaml")


def test_a_vins_fusion_configuration_is_followed_to_its_camera_files(tmp_path):
    (tmp_path / "left.yaml").write_text((DATA / "arclab_plevio_davis346.yaml").read_text())
    (tmp_path / "right.yaml").write_text((DATA / "arclab_iros2022_davis346.yaml").read_text())
    T_imu_cam1 = np.eye(4)
    T_imu_cam1[:3, 3] = [0.1, 0.0, 0.0]
    config = tmp_path / "config.yaml"
    config.write_text(
        '%YAML:1.0\nnum_of_cam: 2\ncam0_calib: "left.yaml"\ncam1_calib: "right.yaml"\n'
        "body_T_cam1: !!opencv-matrix\n   rows: 4\n   cols: 4\n   dt: d\n"
        f"   data: [{', '.join(map(str, T_imu_cam1.ravel()))}]\ntd: 0.004\n"
    )
    right = read_calibration_file(config, "cam1")
    assert fxy(right) == (259.355, 259.58, 177.005, 137.922)  # right.yaml's intrinsics
    np.testing.assert_allclose(right.T_cam_imu[:3, 3], [-0.1, 0, 0])  # the configuration's
    assert right.timeshift_cam_imu_s == 0.004 and right.cameras == ("cam0", "cam1")
    assert "config.yaml + right.yaml" in right.describe()
    left = read_calibration_file(config)
    assert left.T_cam_imu is None  # the configuration has no body_T_cam0
    (tmp_path / "left.yaml").unlink()
    with pytest.raises(InputNotFoundError, match="cam0_calib names left.yaml, not found"):
        read_calibration_file(config)


DV_XML = """<?xml version="1.0"?>
<opencv_storage>
<DAVIS346_00000499>
  <camera_matrix type_id="opencv-matrix">
    <rows>3</rows>
    <cols>3</cols>
    <dt>d</dt>
    <data>
      2.5173e+02 0. 1.7321e+02 0. 2.5102e+02 1.3044e+02 0. 0. 1.</data></camera_matrix>
  <distortion_coefficients type_id="opencv-matrix">
    <rows>5</rows>
    <cols>1</cols>
    <dt>d</dt>
    <data>
      -3.71e-01 1.42e-01 2.1e-04 -3.3e-04 -2.5e-02</data></distortion_coefficients>
  <image_width>346</image_width>
  <image_height>260</image_height>
  {inner}</DAVIS346_00000499>
{second}<type>camera</type>
<use_fisheye_model>0</use_fisheye_model>
<calibration_error>2.1e-01</calibration_error>
</opencv_storage>
"""
SECOND = DV_XML.split("<DAVIS346_00000499>")[1].split("</DAVIS346_00000499>")[0]


def test_dvs_calibration_xml(tmp_path):
    """DV's layout (its camera calibration module's OpenCV FileStorage XML): a camera's element
    with the matrices and the image size; a stereo file has two."""
    path = tmp_path / "calibration_camera_DAVIS346_00000499.xml"
    path.write_text(DV_XML.format(inner="", second=""))
    cal = read_calibration_file(path)
    assert cal.format == "DV calibration XML" and cal.camera == "DAVIS346_00000499"
    assert fxy(cal) == (251.73, 251.02, 173.21, 130.44)
    assert cal.distortion_model == "radtan"
    assert cal.dist.tolist() == [-0.371, 0.142, 2.1e-4, -3.3e-4, -0.025]
    stereo = tmp_path / "stereo.xml"
    second = SECOND.format(inner="").replace("2.5173e+02", "2.6e+02")
    stereo.write_text(
        DV_XML.format(inner="", second=f"<DAVIS346_00000500>{second}</DAVIS346_00000500>\n")
    )
    assert read_calibration_file(stereo, "DAVIS346_00000500").K[0, 0] == 260.0
    assert read_calibration_file(stereo, "cam1").camera == "DAVIS346_00000500"
    with pytest.raises(InputError, match=r"holds 2 \(DAVIS346_00000499, DAVIS346_00000500\)"):
        read_calibration_file(stereo, "DAVIS346_1")


def test_dvs_fisheye_flag_inside_the_cameras_element(tmp_path):
    path = tmp_path / "fisheye.xml"
    text = DV_XML.format(inner="<use_fisheye_model>1</use_fisheye_model>", second="")
    path.write_text(text.replace("<rows>5</rows>", "<rows>4</rows>").replace(" -2.5e-02", ""))
    cal = read_calibration_file(path)
    assert cal.distortion_model == "equidistant" and len(cal.dist) == 4


def camera(**change) -> CameraCalibration:
    """The ESVIO camchain's camera, with its camera-IMU transform, changed as asked."""
    return dataclasses.replace(read_calibration_file(KALIBR_IMU), **change)


def same_camera(a: CameraCalibration, b: CameraCalibration, with_imu: bool) -> None:
    """The same projection (k3 = 0 where one format writes five coefficients and another four)
    and, where the format holds them, the same camera-IMU transform and time shift."""
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_array_equal(a.K, b.K)
    assert a.distortion_model == b.distortion_model
    n = max(len(a.dist), len(b.dist))
    pad = [np.concatenate([d, np.zeros(n - len(d))]) for d in (a.dist, b.dist)]
    np.testing.assert_array_equal(*pad)
    if with_imu:
        np.testing.assert_allclose(b.T_cam_imu, a.T_cam_imu, rtol=0, atol=1e-15)
        assert b.timeshift_cam_imu_s == a.timeshift_cam_imu_s
    else:
        assert b.T_cam_imu is None


@pytest.mark.parametrize(
    ("fmt", "suffix", "holds_imu"),
    [
        ("kalibr", ".yaml", True),
        ("vins", ".yaml", True),
        ("ros", ".yaml", False),
        ("dv", ".xml", False),
    ],
)
@pytest.mark.parametrize("name", READABLE)
def test_every_writer_reads_back_equal(tmp_path, fmt, suffix, holds_imu, name):
    original = read_calibration_file(DATA / name)
    path = tmp_path / f"out{suffix}"
    written, left_out = write_calibration_file(original, path, fmt, name="DAVIS346_00000002")
    assert written == fmt
    back = read_calibration_file(path)
    has_imu = original.T_cam_imu is not None
    same_camera(original, back, with_imu=holds_imu and has_imu)
    assert bool(left_out) == (has_imu and not holds_imu)
    if fmt != "kalibr":
        assert back.camera == "DAVIS346_00000002"


def test_ros_export_carries_camera_calibrations_projection(tmp_path):
    """A monocular camera_info's projection is the undistorted camera (alpha 0), as
    camera_calibration writes it; the rectification the identity."""
    import cv2
    import yaml

    cal = camera()
    path = tmp_path / "ost.yaml"
    write_calibration_file(cal, path, "ros")
    doc = yaml.safe_load(path.read_text())
    assert doc["distortion_model"] == "plumb_bob" and doc["distortion_coefficients"]["cols"] == 5
    assert doc["rectification_matrix"]["data"] == np.eye(3).ravel().tolist()
    coeffs = np.concatenate([cal.dist, [0.0]])
    P, _ = cv2.getOptimalNewCameraMatrix(cal.K, coeffs, (346, 260), 0.0)
    np.testing.assert_allclose(np.reshape(doc["projection_matrix"]["data"], (3, 4))[:, :3], P)


def test_the_default_yaml_is_kalibrs_and_the_extension_decides():
    assert export_format("a.yaml") == "kalibr" and export_format("a.yml", "ros") == "ros"
    assert export_format("a.XML") == "dv"
    with pytest.raises(InputError, match="an .xml file is DV's"):
        export_format("a.xml", "ros")
    with pytest.raises(InputError, match=r"write \.yaml .* or \.xml"):
        export_format("a.json")


def test_what_a_format_cannot_hold_is_refused_naming_the_way_out(tmp_path):
    k3 = camera(dist=np.array([-0.36, 0.13, 0.0, 0.0, 0.01]))
    for fmt in ("kalibr", "vins"):
        with pytest.raises(InputError, match="k3 is 0.01.*--format ros"):
            write_calibration_file(k3, tmp_path / f"{fmt}.yaml", fmt)
    write_calibration_file(k3, tmp_path / "k3.yaml", "ros")
    assert read_calibration_file(tmp_path / "k3.yaml").dist[4] == 0.01
    K = camera().K.copy()
    K[0, 1] = 0.5
    with pytest.raises(InputError, match="skew"):
        write_calibration_file(camera(K=K), tmp_path / "skew.yaml", "kalibr")
    path = tmp_path / "exists.yaml"
    path.write_text("precious: true\n")
    with pytest.raises(OutputExistsError, match="--force"):
        write_calibration_file(camera(), path)
    assert path.read_text() == "precious: true\n"
    write_calibration_file(camera(), path, overwrite=True)
    assert read_calibration_file(path).format == "Kalibr camchain"


def test_a_calibration_of_another_size_is_refused_naming_both():
    cal = read_calibration_file(DATA / "esvo_upenn_davis346_left.yaml")
    with pytest.raises(InputError, match=r"of 346 x 260 images; the sensor of s.h5 is 640 x 480"):
        check_size(cal, 640, 480, "s.h5")


ROS = "image_width: 346\nimage_height: 260\n"
K = "camera_matrix: {rows: 3, cols: 3, data: [250, 0, 173, 0, 250, 130, 0, 0, 1]}\n"
CAM = "cam0: {intrinsics: [250, 250, 173, 130], resolution: [346, 260], "
VINS = "image_width: 346\nimage_height: 260\nprojection_parameters: "
BAD = [
    (
        "scene.yaml",
        "name: a scene\nobjects: [1, 2]\n",
        "not a camera calibration.*has name, objects",
    ),
    ("list.yaml", "- 1\n- 2\n", "not a camera calibration"),
    ("broken.yaml", "cam0: [unclosed\n", "not YAML evcap can read"),
    ("no_width.yaml", K, "no image_width"),
    (
        "rational.yaml",
        ROS + K + "distortion_model: rational_polynomial\n"
        "distortion_coefficients: {rows: 1, cols: 8, data: [1, 2, 3, 4, 5, 6, 7, 8]}\n",
        "distortion_model 'rational_polynomial' is not one evcap takes",
    ),
    (
        "short_k.yaml",
        ROS + "camera_matrix: {rows: 3, cols: 3, data: [250, 0, 173, 0, 250]}\n",
        "camera_matrix says 3 x 3 but holds 5 numbers",
    ),
    (
        "fov.yaml",
        CAM + "distortion_model: fov, distortion_coeffs: [0.9]}\n",
        "cam0: distortion_model 'fov' is not one evcap takes",
    ),
    ("omni.yaml", CAM + "camera_model: omni}\n", "camera_model 'omni'; evcap takes pinhole"),
    ("no_intrinsics.yaml", "cam0: {resolution: [346, 260]}\n", "cam0 has no intrinsics"),
    (
        "negative_f.yaml",
        "cam0: {intrinsics: [-250, 250, 173, 130], resolution: [346, 260]}\n",
        "positive focal lengths",
    ),
    (
        "coefficients.yaml",
        CAM + "distortion_model: equidistant, distortion_coeffs: [0.1, 0.2]}\n",
        "equidistant distortion takes 4 finite coefficients",
    ),
    (
        "not_rotation.yaml",
        CAM + "T_cam_imu: [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}\n",
        "T_cam_imu's rotation is not a rotation",
    ),
    (
        "text_number.yaml",
        "cam0: {intrinsics: [250, fast, 173, 130], resolution: [346, 260]}\n",
        "entries must be a number, got 'fast'",
    ),
    ("mei.yaml", "model_type: MEI\n" + VINS + "{gamma1: 1}\n", "model_type MEI"),
    ("vins_no_fx.yaml", VINS + "{fy: 250, cx: 1, cy: 1}\n", "projection_parameters has no fx"),
    (
        "empty.xml",
        '<?xml version="1.0"?>\n<opencv_storage>\n<type>camera</type>\n</opencv_storage>\n',
        "no camera in it",
    ),
    ("garbage.xml", "<not closed", "not DV's calibration XML"),
    ("truncated.xml", '<?xml version="1.0"?>\n<opencv_storage>\n<cam', "OpenCV reads: parseTag"),
    (
        "short_matrix.xml",
        '<?xml version="1.0"?>\n<opencv_storage>\n<cam><camera_matrix type_id="opencv-matrix">'
        "<rows>3</rows><cols>3</cols><dt>d</dt><data>1 2 3</data></camera_matrix></cam>"
        "</opencv_storage>\n",
        "camera_matrix is not a valid opencv-matrix",
    ),
]


@pytest.mark.parametrize(("name", "text", "message"), BAD, ids=[b[0] for b in BAD])
def test_bad_files_are_refused_naming_the_problem(tmp_path, name, text, message):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(InputError, match=message) as e:
        read_calibration_file(path)
    assert name in str(e.value) and "\n" not in str(e.value) and "persistence" not in str(e.value)


def test_a_missing_file_is_not_found(tmp_path):
    with pytest.raises(InputNotFoundError, match="no such file"):
        read_calibration_file(tmp_path / "none.yaml")


def test_numbers_written_as_yaml_strings_are_read(tmp_path):
    """YAML 1.1 reads `1e-5` (no dot) as a string; the reader takes it as the number it is."""
    path = tmp_path / "kalibr.yaml"
    path.write_text(
        "cam0: {intrinsics: [250, 250, 173, 130], distortion_model: radtan, "
        "distortion_coeffs: [-0.3, 0.1, 1e-5, -2e-5], resolution: [346, 260]}\n"
    )
    assert read_calibration_file(path).dist.tolist() == [-0.3, 0.1, 1e-5, -2e-5]
