"""The monitor daemon: frames from the front end (or the virtual bed) to pressure maps, continuously."""
