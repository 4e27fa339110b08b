"""The MAVLink numbers the project uses, defined once (CONVENTIONS.md, "MAVLink messages").

Enum values keep the dialect's names (``MAV_*``); the project's own names say what the number
is for here. tests/test_mavlink_ids.py holds every value equal to pymavlink's common and
ardupilotmega dialects. They are written out rather than read from pymavlink so that the
importers and replay do not load the dialect (about 20 ms) for a few integers. Message ids are
pymavlink's own (``MAVLINK_MSG_ID_*``) where a module encodes or decodes MAVLink.
"""

from __future__ import annotations

#: MAV_COMP_ID_ONBOARD_COMPUTER: the companion's component id (HEARTBEAT, commands, STATUSTEXT)
COMPANION_COMPONENT = 191
#: MAV_COMP_ID_AUTOPILOT1: the vehicle's component id
MAV_COMP_ID_AUTOPILOT1 = 1
#: MAV_COMP_ID_ALL: a target component of 0 addresses every component
MAV_COMP_ID_ALL = 0

#: ArduCopter's custom_mode number of GUIDED_NOGPS (COPTER_MODE_GUIDED_NOGPS), the mode the
#: companion flies in
GUIDED_NOGPS = 20

#: MAV_SENSOR_ROTATION_PITCH_270: a DISTANCE_SENSOR facing down, the only orientation that is altitude
DOWNWARD = 25
#: DISTANCE_SENSOR ``type``
MAV_DISTANCE_SENSOR_LASER = 0
MAV_DISTANCE_SENSOR_UNKNOWN = 4

#: a velocity setpoint in the local (yaw-rotated) frame
MAV_FRAME_LOCAL_NED = 1
#: the frame of the companion's POSITION_TARGET_LOCAL_NED
MAV_FRAME_BODY_FRD = 12
#: MAV_FRAME_BODY_NED, MAV_FRAME_BODY_OFFSET_NED, MAV_FRAME_BODY_FRD: body-frame velocity setpoints
BODY_FRAMES = (8, 9, 12)

#: MAV_TYPE_GCS, MAV_TYPE_ONBOARD_CONTROLLER: heartbeats that are not the vehicle's
NOT_VEHICLE_TYPES = (6, 18)
#: HEARTBEAT ``autopilot``
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_INVALID = 8
#: HEARTBEAT ``base_mode`` bit: armed
MAV_MODE_FLAG_SAFETY_ARMED = 128
