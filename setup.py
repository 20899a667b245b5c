"""ament_python package playseg_ros; installs the framework-free playseg_core beside it."""

from setuptools import find_packages, setup

PACKAGE = "playseg_ros"

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
    ],
    # Dependencies are pinned in requirements.txt (ROS 2 wheels, torch==2.13.0 CPU) and installed by
    # `make setup`; listing them here would let pip resolve torch to a CUDA build.
    install_requires=[],
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
