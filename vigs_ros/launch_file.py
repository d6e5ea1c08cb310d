"""The graph's ROS launch file (``launch/vigs.launch.xml``) read without the ``launch`` package.

Launch XML is plain XML: ``vigs launch`` takes its nodes, parameter files and remaps from the same file that
``ros2 launch vigs_ros vigs.launch.xml`` runs, so the two cannot drift apart. Only what that file uses is
understood: ``<arg name default>``, ``<node pkg exec name>`` with ``<param from>`` and ``<remap from to>``, and
the substitutions ``$(var NAME)`` and ``$(find-pkg-share vigs_ros)`` (the checkout's root, or the installed
share folder, both holding ``params/``); anything else is an error naming the file.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

PACKAGE = "vigs_ros"


def package_share() -> Path:
    """The folder holding ``launch/`` and ``params/``: the checkout (a source or editable install), else the
    installed share folder found through the ament index (a colcon install)."""
    checkout = Path(__file__).resolve().parent.parent
    if (checkout / "launch" / "vigs.launch.xml").is_file():
        return checkout
    from ament_index_python.packages import get_package_share_directory

    return Path(get_package_share_directory(PACKAGE))


PACKAGE_SHARE = package_share()
LAUNCH_FILE = PACKAGE_SHARE / "launch" / "vigs.launch.xml"
_SUBSTITUTION = re.compile(r"\$\(([\w-]+)\s+([^)]*)\)")


@dataclass
class LaunchNode:
    """One ``<node>``: ``name``, executable ``exec``, parameter files in order, remaps ``(from, to)``."""

    name: str
    exec: str
    params: list[Path] = field(default_factory=list)
    remaps: list[tuple[str, str]] = field(default_factory=list)


def read_launch_file(path: str | Path = LAUNCH_FILE) -> list[LaunchNode]:
    """The nodes of a launch XML file, in start order (module docstring); ValueError for what is not understood."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as e:
        raise ValueError(f"launch file {path}: {e}") from None
    if root.tag != "launch":
        raise ValueError(f"launch file {path}: root element <{root.tag}>, expected <launch>")
    args: dict[str, str] = {}

    def resolve(text: str) -> str:
        def one(m: re.Match) -> str:
            kind, value = m.group(1), m.group(2).strip()
            if kind == "var" and value in args:
                return args[value]
            if kind == "find-pkg-share" and value == PACKAGE:
                return str(PACKAGE_SHARE)
            raise ValueError(f"launch file {path}: unsupported substitution $({kind} {value})")
        return _SUBSTITUTION.sub(one, text)

    nodes = []
    for element in root:
        if element.tag == "arg":
            args[element.attrib["name"]] = resolve(element.attrib.get("default", ""))
        elif element.tag == "node":
            if element.attrib.get("pkg") != PACKAGE:
                raise ValueError(f"launch file {path}: node of package {element.attrib.get('pkg')!r}, "
                                 f"expected {PACKAGE!r}")
            node = LaunchNode(element.attrib["name"], element.attrib["exec"])
            for child in element:
                if child.tag == "param" and "from" in child.attrib:
                    node.params.append(Path(resolve(child.attrib["from"])))
                elif child.tag == "remap":
                    node.remaps.append((resolve(child.attrib["from"]), resolve(child.attrib["to"])))
                else:
                    raise ValueError(f"launch file {path}: unsupported <{child.tag}> in node {node.name!r}")
            nodes.append(node)
        else:
            raise ValueError(f"launch file {path}: unsupported element <{element.tag}>")
    return nodes
