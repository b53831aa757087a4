"""The desktop bundle's executable: the ``hapticloud`` command line (packaging/hapticloud.spec)."""

import multiprocessing
import sys

if __name__ == "__main__":
    # The control process, the recorder and the benches start 'spawn' children: in the bundle
    # they re-run this executable, and freeze_support() turns such a run into the child.
    multiprocessing.freeze_support()
    from hapticloud.app.cli import main

    sys.exit(main())
