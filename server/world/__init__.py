"""The live robot worlds of the sessions this process serves (server memory, rebuilt on demand).

Every trial's scene and autonomous attempt are deterministic in (study seed, participant, block, trial), so nothing
here needs to survive a restart: the database holds the trial's stage and deadlines, and the world of any trial can
be rebuilt from them. ``docs/architecture.md`` tells how the parts fit:

- ``hub``: ``WorldHub``, the 30 Hz loop that advances every teleoperated arm and hands the watched worlds to the
  sockets and the 3D views;
- ``teleop``: one teleoperation (``TeleopSession``, its log) and the clock that moves the arms under held input;
- ``attempts``: scenes and the autonomous attempts, planned ahead in helper processes;
- ``playback``: attempts being shown, and the frames the world sends;
- ``physics``: the helper process that moves many arms at once;
- ``processes``: how helper processes are started and end with the server.
"""
