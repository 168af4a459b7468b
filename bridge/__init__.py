"""Hardware in the loop over Zenoh (docs/hil.md): a live robot stands where a Vehicle FMU would.

``live`` is the run's side of the link (``LiveVehicle``, the orchestrator's component for a robot),
``emulator`` stands in for the robots and their motion capture, ``serial_endpoint`` forwards a run's
wheel commands to a real m3pi over an XBee, ``mocap`` publishes a motion capture's rigid bodies as
poses. ``protocol`` (keys, messages, checks), ``claim`` (one run per robot), ``states`` (the link's
states), ``session`` (Zenoh sessions) and ``lab`` (a secure lab's certificates) are what they share;
``ros2`` speaks the same on ROS 2 topics. The bridge knows Zenoh and the model, not FMI internals."""
