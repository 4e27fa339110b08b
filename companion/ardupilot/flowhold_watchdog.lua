-- flowhold_watchdog.lua: an ArduCopter applet that outlives the flowhold companion (issue 18).
--
-- While the vehicle is armed in GUIDED_NOGPS, the flowhold companion (MAVLink component 191 of
-- this vehicle's system) commands it with SET_ATTITUDE_TARGET at the flow frame rate. When those
-- commands stop (the companion killed, hung or unplugged), ArduCopter alone levels the vehicle
-- after GUID_TIMEOUT, raises no failsafe and says nothing, and a level vehicle drifts with the wind
-- (on SITL: 19.3 m in 10 s in a 3 m/s wind). This applet says so (STATUSTEXT CRITICAL) and switches
-- to FHW_MODE once the commands have stopped for FHW_TIMEOUT seconds: once per GUIDED_NOGPS
-- episode, and never while the companion commands or the vehicle is in another mode.
--
-- Parameters (the scripting parameter table FHW_, created on the first run):
--   FHW_ENABLE   1 watch, 0 do nothing                                           (default 1)
--   FHW_TIMEOUT  s without a SET_ATTITUDE_TARGET from the companion before acting (default 1)
--   FHW_MODE     the mode to switch to: 9 LAND, 2 ALT_HOLD, 17 BRAKE (BRAKE needs a position
--                estimate; if the mode is refused, LAND is tried)                 (default 9)
--
-- Install: SCR_ENABLE 1, reboot, copy this file into the scripts folder (APM/scripts on the SD
-- card; beside the eeprom for SITL), reboot. Written by `python -m companion ardupilot-script`.
--
-- Bindings used (ArduPilot scripting): param:add_table, param:add_param, param:get,
-- mavlink:init, mavlink:register_rx_msgid, mavlink:receive_chan, vehicle:get_mode,
-- vehicle:set_mode, arming:is_armed, gcs:send_text, millis.

local PARAM_TABLE_KEY = 91
local PARAM_TABLE_PREFIX = "FHW_"
local GUIDED_NOGPS = 20
local LAND = 9
local COMPANION_COMPID = 191 -- MAV_COMP_ID_ONBOARD_COMPUTER
local MSG_HEARTBEAT = 0
local MSG_SET_ATTITUDE_TARGET = 82
local SEVERITY_CRITICAL = 2
local SEVERITY_NOTICE = 5
local UPDATE_MS = 50
local MAX_MESSAGES_PER_UPDATE = 25
local MODE_NAMES = { [0] = "STABILIZE", [2] = "ALT_HOLD", [5] = "LOITER", [9] = "LAND", [17] = "BRAKE",
                     [20] = "GUIDED_NOGPS" }

assert(param:add_table(PARAM_TABLE_KEY, PARAM_TABLE_PREFIX, 3), "flowhold watchdog: cannot add the FHW_ table")
assert(param:add_param(PARAM_TABLE_KEY, 1, "ENABLE", 1), "flowhold watchdog: cannot add FHW_ENABLE")
assert(param:add_param(PARAM_TABLE_KEY, 2, "TIMEOUT", 1.0), "flowhold watchdog: cannot add FHW_TIMEOUT")
assert(param:add_param(PARAM_TABLE_KEY, 3, "MODE", LAND), "flowhold watchdog: cannot add FHW_MODE")

-- the receive queue's depth and the number of message ids: ArduPilot releases document the two
-- arguments in either order; 10 and 10 suit both
mavlink:init(10, 10)
mavlink:register_rx_msgid(MSG_HEARTBEAT)
mavlink:register_rx_msgid(MSG_SET_ATTITUDE_TARGET)

local function mode_name(mode)
  return MODE_NAMES[mode] or string.format("MODE%d", mode)
end

local function own_sysid()
  return param:get("MAV_SYSID") or param:get("SYSID_THISMAV") -- (renamed in ArduPilot 4.7)
end

local watching = false -- armed in GUIDED_NOGPS, FHW_ENABLE 1
local episode_ms = 0 -- when the current GUIDED_NOGPS episode began
local command_ms = nil -- the companion's last SET_ATTITUDE_TARGET
local heartbeat_ms = nil -- the companion's last HEARTBEAT
local acted = false -- the switch was made (or tried) in this episode

-- the companion's messages: a received message is the bytes of ArduPilot's mavlink_message_t:
-- checksum (2), magic, len, incompat_flags, compat_flags, seq, sysid, compid, msgid (3), payload
local function read_messages(now_ms)
  local sysid = own_sysid()
  for _ = 1, MAX_MESSAGES_PER_UPDATE do
    local msg = mavlink:receive_chan()
    if not msg then
      return
    end
    local msg_sysid, compid, msgid = string.unpack("<BBI3", msg, 8)
    if compid == COMPANION_COMPID and (sysid == nil or msg_sysid == sysid) then
      if msgid == MSG_SET_ATTITUDE_TARGET then
        command_ms = now_ms
      elseif msgid == MSG_HEARTBEAT then
        heartbeat_ms = now_ms
      end
    end
  end
end

-- the commands have stopped for more than FHW_TIMEOUT: say it (with the timeout), switch mode
local function act(now_ms, timeout_ms)
  acted = true
  local mode = math.floor(param:get("FHW_MODE") or LAND)
  local alive = heartbeat_ms ~= nil and now_ms - heartbeat_ms <= timeout_ms
  local why = alive and "no commands" or "companion lost"
  gcs:send_text(SEVERITY_CRITICAL, string.format("flowhold watchdog: %s %.1f s: %s", why, timeout_ms / 1000.0,
                                                 mode_name(mode)))
  if vehicle:set_mode(mode) then
    return
  end
  gcs:send_text(SEVERITY_CRITICAL, string.format("flowhold watchdog: %s refused", mode_name(mode)))
  if mode ~= LAND and vehicle:set_mode(LAND) then
    gcs:send_text(SEVERITY_CRITICAL, "flowhold watchdog: LAND instead")
  end
end

local function update()
  local now_ms = millis():tofloat()
  read_messages(now_ms)
  local enabled = (param:get("FHW_ENABLE") or 0) >= 1
  if not (enabled and arming:is_armed() and vehicle:get_mode() == GUIDED_NOGPS) then
    watching = false
    return
  end
  if not watching then -- a new episode: commands from before it do not count
    watching = true
    acted = false
    episode_ms = now_ms
  end
  local since_ms = episode_ms
  if command_ms ~= nil and command_ms > since_ms then
    since_ms = command_ms
  end
  local timeout_ms = (param:get("FHW_TIMEOUT") or 1.0) * 1000.0
  if not acted and now_ms - since_ms > timeout_ms then
    act(now_ms, timeout_ms)
  end
end

-- an error must not stop the watchdog silently: say it, and go on
local function protected_update()
  local ok, err = pcall(update)
  if not ok then
    gcs:send_text(SEVERITY_CRITICAL, "flowhold watchdog: error: " .. tostring(err))
    return protected_update, 1000
  end
  return protected_update, UPDATE_MS
end

gcs:send_text(SEVERITY_NOTICE, "flowhold watchdog: watching GUIDED_NOGPS")
return protected_update, UPDATE_MS
