"""stg_node: STG-Avatar animatable Gaussian avatars as ROS-free telepresence nodes.

Subpackages are imported on demand; importing this package stays cheap so that
torch-free parts (the bus, proto tools) start fast.
"""

__version__ = "0.1.0"
