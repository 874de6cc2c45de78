"""stg-launch: YAML launch files -> a broker and supervised node processes (docs/LAUNCH.md).

:mod:`.yamlfile` reads YAML safely with line numbers, :mod:`.substitute` resolves ``$(...)``,
:mod:`.spec` checks a file into a LaunchSpec, :mod:`.schema` is its JSON schema,
:mod:`.process` runs one child in its own process group, :mod:`.supervisor` runs the launch.
"""

from stg_node.launch.spec import LaunchSpec, NodeSpec, parse_overrides, read_launch
from stg_node.launch.yamlfile import LaunchFileError

__all__ = ["LaunchFileError", "LaunchSpec", "NodeSpec", "parse_overrides", "read_launch"]
