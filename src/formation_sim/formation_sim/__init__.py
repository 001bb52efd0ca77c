"""The world of a formation and everything that runs it: ``core`` (ROS-free plant, measurements,
closed loop, judge, recorder), ``node`` (the simulator node), ``launch`` (the launcher of a ROS 2
run), ``offline`` (runs from a recorded bag), ``views`` (figures, animation, markers, run outputs),
``cli`` (the console scripts), with :mod:`preflight` (the checks before any run starts) and
:mod:`capacity` (what a host holds in realtime)."""
