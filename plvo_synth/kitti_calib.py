"""KITTI's calibrations, embedded in the package so that a twin carries its own sequence's camera, image size and
lidar extrinsic (the KITTI data itself is not shipped).

Odometry 00-02 were recorded on 2011-10-03 (1241x376 images), 04-10 on 2011-09-30 (1226x370) and 03 on 2011-09-26,
the day of raw drive 0009: 03's calib.txt is that day's raw calibration in odometry form (P0..P3 = P_rect_00..03,
Tr = R_rect_00 @ [R|T] of calib_velo_to_cam.txt; 1242x375), as KITTI's own 03 calib.txt has it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plvo.errors import SynthError
from plvo_synth.sensors import IMAGE_HEIGHT, IMAGE_WIDTH, KITTI_CALIB_00_TEXT

# calib.txt of KITTI odometry sequences 04-10 (recorded 2011-09-30), verbatim.
CALIB_04_10_TEXT = (
    "P0: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 0.000000000000e+00 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 0.000000000000e+00 0.000000000000e+00 "
    "0.000000000000e+00 1.000000000000e+00 0.000000000000e+00\n"
    "P1: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 -3.798145000000e+02 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 0.000000000000e+00 0.000000000000e+00 "
    "0.000000000000e+00 1.000000000000e+00 0.000000000000e+00\n"
    "P2: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 4.688783000000e+01 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 1.178601000000e-01 0.000000000000e+00 "
    "0.000000000000e+00 1.000000000000e+00 6.203223000000e-03\n"
    "P3: 7.070912000000e+02 0.000000000000e+00 6.018873000000e+02 -3.334597000000e+02 "
    "0.000000000000e+00 7.070912000000e+02 1.831104000000e+02 1.930130000000e+00 0.000000000000e+00 "
    "0.000000000000e+00 1.000000000000e+00 3.318498000000e-03\n"
    "Tr: -1.857739385241e-03 -9.999659513510e-01 -8.039975204516e-03 -4.784029760483e-03 "
    "-6.481465826011e-03 8.051860151134e-03 -9.999466081774e-01 -7.337429464231e-02 "
    "9.999773098287e-01 -1.805528627661e-03 -6.496203536139e-03 -3.339968064433e-01\n"
)

# The raw recording day 2011-09-26 (odometry 03, raw drive 0009): its three calibration files, verbatim.
RAW_2011_09_26_CAM_TO_CAM = (
    "calib_time: 09-Jan-2012 13:57:47\n"
    "corner_dist: 9.950000e-02\n"
    "S_00: 1.392000e+03 5.120000e+02\n"
    "K_00: 9.842439e+02 0.000000e+00 6.900000e+02 0.000000e+00 9.808141e+02 2.331966e+02 "
    "0.000000e+00 0.000000e+00 1.000000e+00\n"
    "D_00: -3.728755e-01 2.037299e-01 2.219027e-03 1.383707e-03 -7.233722e-02\n"
    "R_00: 1.000000e+00 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00 "
    "0.000000e+00 0.000000e+00 1.000000e+00\n"
    "T_00: 2.573699e-16 -1.059758e-16 1.614870e-16\n"
    "S_rect_00: 1.242000e+03 3.750000e+02\n"
    "R_rect_00: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 "
    "7.402527e-03 4.351614e-03 9.999631e-01\n"
    "P_rect_00: 7.215377e+02 0.000000e+00 6.095593e+02 0.000000e+00 0.000000e+00 7.215377e+02 "
    "1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00\n"
    "S_01: 1.392000e+03 5.120000e+02\n"
    "K_01: 9.895267e+02 0.000000e+00 7.020000e+02 0.000000e+00 9.878386e+02 2.455590e+02 "
    "0.000000e+00 0.000000e+00 1.000000e+00\n"
    "D_01: -3.644661e-01 1.790019e-01 1.148107e-03 -6.298563e-04 -5.314062e-02\n"
    "R_01: 9.993513e-01 1.860866e-02 -3.083487e-02 -1.887662e-02 9.997863e-01 -8.421873e-03 "
    "3.067156e-02 8.998467e-03 9.994890e-01\n"
    "T_01: -5.370000e-01 4.822061e-03 -1.252488e-02\n"
    "S_rect_01: 1.242000e+03 3.750000e+02\n"
    "R_rect_01: 9.996878e-01 -8.976826e-03 2.331651e-02 8.876121e-03 9.999508e-01 4.418952e-03 "
    "-2.335503e-02 -4.210612e-03 9.997184e-01\n"
    "P_rect_01: 7.215377e+02 0.000000e+00 6.095593e+02 -3.875744e+02 0.000000e+00 7.215377e+02 "
    "1.728540e+02 0.000000e+00 0.000000e+00 0.000000e+00 1.000000e+00 0.000000e+00\n"
    "S_02: 1.392000e+03 5.120000e+02\n"
    "K_02: 9.597910e+02 0.000000e+00 6.960217e+02 0.000000e+00 9.569251e+02 2.241806e+02 "
    "0.000000e+00 0.000000e+00 1.000000e+00\n"
    "D_02: -3.691481e-01 1.968681e-01 1.353473e-03 5.677587e-04 -6.770705e-02\n"
    "R_02: 9.999758e-01 -5.267463e-03 -4.552439e-03 5.251945e-03 9.999804e-01 -3.413835e-03 "
    "4.570332e-03 3.389843e-03 9.999838e-01\n"
    "T_02: 5.956621e-02 2.900141e-04 2.577209e-03\n"
    "S_rect_02: 1.242000e+03 3.750000e+02\n"
    "R_rect_02: 9.998817e-01 1.511453e-02 -2.841595e-03 -1.511724e-02 9.998853e-01 -9.338510e-04 "
    "2.827154e-03 9.766976e-04 9.999955e-01\n"
    "P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 "
    "1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03\n"
    "S_03: 1.392000e+03 5.120000e+02\n"
    "K_03: 9.037596e+02 0.000000e+00 6.957519e+02 0.000000e+00 9.019653e+02 2.242509e+02 "
    "0.000000e+00 0.000000e+00 1.000000e+00\n"
    "D_03: -3.639558e-01 1.788651e-01 6.029694e-04 -3.922424e-04 -5.382460e-02\n"
    "R_03: 9.995599e-01 1.699522e-02 -2.431313e-02 -1.704422e-02 9.998531e-01 -1.809756e-03 "
    "2.427880e-02 2.223358e-03 9.997028e-01\n"
    "T_03: -4.731050e-01 5.551470e-03 -5.250882e-03\n"
    "S_rect_03: 1.242000e+03 3.750000e+02\n"
    "R_rect_03: 9.998321e-01 -7.193136e-03 1.685599e-02 7.232804e-03 9.999712e-01 -2.293585e-03 "
    "-1.683901e-02 2.415116e-03 9.998553e-01\n"
    "P_rect_03: 7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0.000000e+00 7.215377e+02 "
    "1.728540e+02 2.199936e+00 0.000000e+00 0.000000e+00 1.000000e+00 2.729905e-03\n"
)

RAW_2011_09_26_IMU_TO_VELO = (
    "calib_time: 25-May-2012 16:47:16\n"
    "R: 9.999976e-01 7.553071e-04 -2.035826e-03 -7.854027e-04 9.998898e-01 -1.482298e-02 "
    "2.024406e-03 1.482454e-02 9.998881e-01\n"
    "T: -8.086759e-01 3.195559e-01 -7.997231e-01\n"
)

RAW_2011_09_26_VELO_TO_CAM = (
    "calib_time: 15-Mar-2012 11:37:16\n"
    "R: 7.533745e-03 -9.999714e-01 -6.166020e-04 1.480249e-02 7.280733e-04 -9.998902e-01 "
    "9.998621e-01 7.523790e-03 1.480755e-02\n"
    "T: -4.069766e-03 -7.631618e-02 -2.717806e-01\n"
    "delta_f: 0.000000e+00 0.000000e+00\n"
    "delta_c: 0.000000e+00 0.000000e+00\n"
)

RAW_CALIB_FILES = ("calib_cam_to_cam.txt", "calib_imu_to_velo.txt", "calib_velo_to_cam.txt")


def parse_calib_text(text: str) -> dict[str, np.ndarray]:
    """KITTI calib text -> {key: values} for every line whose values are all numbers (calib_time is skipped)."""
    out = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        try:
            numbers = np.array([float(x) for x in value.split()])
        except ValueError:
            continue
        if sep and len(numbers):
            out[key.strip()] = numbers
    return out


def rigid(values: dict[str, np.ndarray]) -> np.ndarray:
    """A calib file's R and T -> (4,4)."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = values["R"].reshape(3, 3), values["T"]
    return T


def _row(key: str, M: np.ndarray) -> str:
    return f"{key}: " + " ".join(f"{x:.12e}" for x in np.asarray(M, np.float64).ravel()) + "\n"


@dataclass(frozen=True)
class KittiCalibration:
    """One KITTI calibration: name ("00-02", "04-10" or a raw day "2011_09_26"), calib.txt in the odometry layout,
    cam0's image size, and for a raw day its calib_*.txt files (name, text)."""

    name: str
    odometry_text: str
    width: int
    height: int
    raw_files: tuple[tuple[str, str], ...] = ()

    def matrix(self, key: str) -> np.ndarray:
        return parse_calib_text(self.odometry_text)[key].reshape(3, 4)

    @property
    def K(self) -> np.ndarray:
        return self.matrix("P0")[:, :3].copy()

    @property
    def T_cam_velo(self) -> np.ndarray:
        """(4,4) rectified cam0 <- Velodyne."""
        return np.vstack([self.matrix("Tr"), [0.0, 0.0, 0.0, 1.0]])

    def odometry_text_with(self, T_cam_velo: np.ndarray) -> str:
        """calib.txt with Tr replaced by T_cam_velo (the extrinsic a twin's files state)."""
        lines = [ln + "\n" for ln in self.odometry_text.splitlines() if not ln.startswith("Tr:")]
        return "".join(lines) + _row("Tr", np.asarray(T_cam_velo)[:3])

    def raw_texts_with(self, T_cam_velo: np.ndarray) -> dict[str, str]:
        """The raw day's calib_*.txt, calib_velo_to_cam.txt stating T_cam_velo (rectified cam0 <- Velodyne) as
        KITTI does: [R|T] to the unrectified cam0, R_rect_00 @ [R|T] = T_cam_velo."""
        if not self.raw_files:
            raise SynthError(f"calibration {self.name}: not a raw recording day's")
        files = dict(self.raw_files)
        rect = np.eye(4)
        rect[:3, :3] = parse_calib_text(files["calib_cam_to_cam.txt"])["R_rect_00"].reshape(3, 3)
        T = np.linalg.inv(rect) @ np.asarray(T_cam_velo, np.float64)
        head = [ln + "\n" for ln in files["calib_velo_to_cam.txt"].splitlines() if ln.split(":")[0] not in ("R", "T")]
        files["calib_velo_to_cam.txt"] = "".join(head[:1] + [_row("R", T[:3, :3]), _row("T", T[:3, 3])] + head[1:])
        return files


def raw_day_calibration(name: str, texts: dict[str, str]) -> KittiCalibration:
    """A raw recording day's calib_*.txt texts -> its calibration, calib.txt in odometry form (see the module)."""
    cam = parse_calib_text(texts["calib_cam_to_cam.txt"])
    rect = np.eye(4)
    rect[:3, :3] = cam["R_rect_00"].reshape(3, 3)
    Tr = rect @ rigid(parse_calib_text(texts["calib_velo_to_cam.txt"]))
    text = "".join(_row(f"P{c}", cam[f"P_rect_0{c}"]) for c in range(4)) + _row("Tr", Tr[:3])
    width, height = (int(round(x)) for x in cam["S_rect_00"])
    return KittiCalibration(name, text, width, height, tuple((f, texts[f]) for f in RAW_CALIB_FILES))


CALIB_00_02 = KittiCalibration("00-02", KITTI_CALIB_00_TEXT, IMAGE_WIDTH, IMAGE_HEIGHT)
CALIB_04_10 = KittiCalibration("04-10", CALIB_04_10_TEXT, 1226, 370)
CALIB_2011_09_26 = raw_day_calibration("2011_09_26", {
    "calib_cam_to_cam.txt": RAW_2011_09_26_CAM_TO_CAM, "calib_imu_to_velo.txt": RAW_2011_09_26_IMU_TO_VELO,
    "calib_velo_to_cam.txt": RAW_2011_09_26_VELO_TO_CAM})
_ODOMETRY_DAY = {"00": CALIB_00_02, "01": CALIB_00_02, "02": CALIB_00_02, "03": CALIB_2011_09_26,
                 **{f"{k:02d}": CALIB_04_10 for k in range(4, 11)}}


def odometry_calibration(sequence: str) -> KittiCalibration:
    """KITTI odometry sequence NN's own calibration (00-10); any other number keeps 00-02's."""
    return _ODOMETRY_DAY.get(sequence, CALIB_00_02)
