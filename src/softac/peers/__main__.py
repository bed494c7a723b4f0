"""`python -m softac.peers run|throughput|solve PEER ...`: see softac.peers."""

import sys

from softac.peers.runs import main

if __name__ == "__main__":
    from softac.base.stop_signal import finish_after_stop

    finish_after_stop()  # a process of its own (a sweep's trial): see there
    main(sys.argv[1:])
