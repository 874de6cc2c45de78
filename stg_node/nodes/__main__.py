"""``python -m stg_node.nodes KIND ...``: run one node as a process (stg_node.cli.node)."""

import sys

from stg_node.cli.node import main

sys.exit(main())
