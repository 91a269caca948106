"""Sessions in MCAP (docs/DESIGN.md section 5): ``schema`` (topics, message schemas, decoders), ``writer``
(recording), ``reader`` (replay and the readers of clouds, units and documents), ``recovery`` (cut
recordings).

Layout of a recording, per sensor ``<id>`` (all messages of one frame share log_time = its timestamp_ns):

- ``/camera/<id>/depth``        ROS 2 sensor_msgs/msg/Image "16UC1" (CDR), the raw little-endian uint16
                                depth units
- ``/camera/<id>/color``        foxglove.RawImage "rgb8", when the frame has colour
- ``/camera/<id>/calibration``  foxglove.CameraCalibration (K, P, plumb_bob with zero D)
- ``/tf``                       foxglove.FrameTransforms world -> camera/<id>, when the pose is known
- ``/camera/<id>/meta``         JSON ``{"timestamp_ns", "depth_scale", "turntable_angle", "T_world_camera",
                                "has_color"}``

Depth is a ROS 2 Image, not a foxglove.RawImage, because viewers show that schema's 16UC1 as depth:
Rerun's MCAP import makes it a DepthImage (a foxglove.RawImage becomes a grey image), and Foxglove reads
ROS 2 messages natively. Recordings whose depth is a foxglove.RawImage are read as well.
The foxglove schemas have no field for a depth scale or a turntable angle, and a pose stored as a
quaternion does not come back bit-exact, so the meta channel carries what replay needs exactly
(JSON floats round-trip exactly); /tf is there for viewers. The meta message also says whether a
colour image belongs to the frame, so the reader knows when a frame is complete.
"""
