"""The sim CLI writes a frame, a point cloud and a landmark list that read back."""

import json

import cv2

from openfly_agent.sim.city import CityConfig, generate_city
from openfly_agent.sim.cli import main
from openfly_agent.sim.pointcloud import read_points


def test_export_landmarks_and_render(tmp_path, capsys):
    common = ["--seed", "3", "--size-m", "300"]
    main(["export", *common, "--out", str(tmp_path / "c.pcd"), "--spacing", "4"])
    city = generate_city(3, CityConfig(size_m=300.0))
    assert len(read_points(tmp_path / "c.pcd")) == len(city.point_cloud(4.0))
    main(["landmarks", *common, "--out", str(tmp_path / "l.jsonl")])
    records = [json.loads(line) for line in (tmp_path / "l.jsonl").read_text().splitlines()]
    assert [r["landmark_id"] for r in records] == [lm.landmark_id for lm in city.landmarks]
    assert records[0]["description"] == city.landmarks[0].description()
    main(["render", *common, "--pose", "-160", "-160", "60", "0.8", "--width", "48", "--height", "32",
          "--boxes", "--out", str(tmp_path / "f.png")])  # fmt: skip
    assert cv2.imread(str(tmp_path / "f.png")).shape == (32, 48, 3)
    assert "landmark boxes" in capsys.readouterr().out
