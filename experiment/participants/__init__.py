"""Models of people taking part in a study: pure Python and numpy, no server, no database, no browser.

- ``reliance``: a participant who relies on the robot or intervenes as an IOHMM says (hidden trust moved by each
  trial's experience); the in-process study simulation (``experiment.simulate``) and the bots run it.
- The teleoperating participant, who sees only what the teleoperation socket sends (a test checks that these
  modules import nothing of the robot's code):

  - ``keys``: the page's keys and how it turns held keys into an input message;
  - ``mast``: where the arm turns about, estimated from the poses seen;
  - ``teleoperator``: the strategy of a person who has read the instructions (``Operator``);
  - ``person``: the person around it: reaction time, perceptual noise, anticipation (``HumanModel``);
  - ``page``: the page's loop between the person and the socket (``ClientLoop``).
"""
