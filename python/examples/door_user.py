"""Opens the door, then watches its state for a second."""
import sys

import muster

with muster.User(instance=sys.argv[1] if len(sys.argv) > 1 else "default") as me:
    print([s.id for s in me.list()])
    with me.request("door/open") as door:
        door.send("open")
        print(door.wait_status("done", timeout=10).detail)
    with me.request("door/state") as state:
        for update in state.updates(timeout=1.5):
            print(update.seq, update.value)
            if update.seq >= 5:
                break
