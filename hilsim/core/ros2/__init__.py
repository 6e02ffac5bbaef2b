"""ROS 2 on the wire: type descriptions and hashes, rmw_zenoh keys, attachments and graph tokens."""
