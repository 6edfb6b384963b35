"""occ-ros2: a bridge from the OCC daemons' OpenIGTLink interfaces to ROS 2 over DDS.

Optional (``pip install -e .[ros2]``): it needs ``cyclonedds``, which the core packages
``igtl`` and ``occ`` never import. The bridge is an ordinary OpenIGTLink client of the daemons
(docs/ROS2.md), so the daemons know nothing of ROS 2.
"""
