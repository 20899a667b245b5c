"""ament_python package playseg_ros; installs the framework-free playseg_core beside it."""

from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "playseg_ros"
ROOT = Path(__file__).resolve().parent


def pins(requirements: str) -> list[str]:
    """The exact pins of a requirements file (comments and blank lines left out)."""
    lines = (line.split("#")[0].strip() for line in (ROOT / requirements).read_text().splitlines())
    return [line for line in lines if line]


setup(
    name=PACKAGE,
    version="0.1.0",
    description="Play Segmentation for ROS 2 play recordings (PS, AAAI 2025)",
    license="Apache-2.0",
    python_requires=">=3.11,<3.12",
    packages=find_packages(include=["playseg_core", "playseg_core.*", "playseg_ros", "playseg_ros.*"]),
    package_data={"playseg_ros.review": ["static/*"]},  # the review page
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        # playseg_msgs' definitions, for reading bags where the interface package is not built (the I/O
        # part alone); relative paths, as setuptools wants them
        (
            f"share/{PACKAGE}/msg",
            sorted(str(p.relative_to(ROOT)) for p in (ROOT / "msg_defs/playseg_msgs/msg").glob("*.msg")),
        ),
    ],
    # Dependencies are pinned in requirements.txt (ROS 2 wheels, torch==2.13.0 CPU) and installed by
    # `make setup`; listing them here would let pip resolve torch to a CUDA build.
    install_requires=[],
    # The ROS-free I/O part alone (`playseg bag`, `playseg convert`, the LeRobot export): pip install '.[io]'
    # installs requirements-io.txt's pins, no ROS 2 wheels and no torch (docs/setup.md).
    extras_require={"io": pins("requirements-io.txt")},
    entry_points={
        "console_scripts": [
            "playseg = playseg_ros.cli:main",
            "playseg-recorder = playseg_ros.nodes.recorder:main",
            "playseg-segmenter = playseg_ros.nodes.segmenter:main",
            "playseg-trainer = playseg_ros.nodes.trainer:main",
            "playseg-play-source = playseg_ros.babyai.play_source:main",
            "playseg-bag-player = playseg_ros.nodes.bag_player:main",
            "playseg-topic-adapter = playseg_ros.nodes.topic_adapter:main",
        ],
    },
)
