"""``ucr view``: the robot live in a browser (true arcs from the model plugins, task-space control).

Its own process: a client of the daemon's API (the control loop never waits for it), or offline on a
U(C)RDF file. :mod:`view.scene` computes what to draw (no web dependency), :mod:`view.app` draws it
with viser, :mod:`view.source` feeds it (daemon or file), :mod:`view.control` moves the robot.
"""
