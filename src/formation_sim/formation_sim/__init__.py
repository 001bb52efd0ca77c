"""The world of a formation and everything that runs it: ``core`` (ROS-free plant, measurements,
closed loop, recorder), ``node`` (the simulator node), ``launch`` (the launcher of a ROS 2 run),
``views`` (figures, animation, markers, run outputs) and ``cli`` (the console scripts)."""
