"""A door: `open` (a command: "opening", then "open" 2 s later) and `state` (5 Hz)."""
import sys
import muster

door = muster.System("door", instance=sys.argv[1] if len(sys.argv) > 1 else "default")
is_open = False


@door.command_service("open", payload="text", quota=1, queue=True)
def open_door(session, value):
    session.working("opening")
    def opened():
        global is_open
        is_open = True
        session.done("open")
    door.after(2.0, opened)


@door.data_service("state", payload="text", rate=5)
def state():
    return "open" if is_open else "closed"


door.run()
