-- The flowhold watchdog applet's logic under mocked ArduPilot bindings, on a stock Lua 5.4.
--
--   lua5.4 tests/lua/watchdog_spec.lua flowhold_watchdog.lua
--
-- Each scenario loads the applet in a fresh environment whose bindings (param, mavlink, vehicle,
-- arming, gcs, millis) are tables recording what the applet does, runs the scheduler as ArduPilot
-- does (the applet returns its function and the delay before the next call), and feeds it the
-- companion's messages as ArduPilot's mavlink_message_t bytes. Exits non-zero on the first failure.

local path = assert(arg[1], "usage: lua5.4 watchdog_spec.lua flowhold_watchdog.lua")

local GUIDED_NOGPS, STABILIZE, ALT_HOLD, LAND, BRAKE = 20, 0, 2, 9, 17
local HEARTBEAT, SET_ATTITUDE_TARGET = 0, 82
local CRITICAL, NOTICE = 2, 5

-- ArduPilot's mavlink_message_t: checksum (2), magic, len, incompat, compat, seq, sysid, compid, msgid (3)
local function message(sysid, compid, msgid)
  return string.pack("<I2BBBBBBBI3", 0xBEEF, 0xFD, 0, 0, 0, 0, sysid, compid, msgid) .. string.rep("\0", 8)
end

local function world(opts)
  opts = opts or {}
  local w = { now = 0.0, mode = opts.mode or GUIDED_NOGPS, armed = opts.armed ~= false, texts = {},
              set_modes = {}, queue = {}, params = {}, tables = {}, rx = {}, refuse = opts.refuse or {},
              sysid = opts.sysid or 1, senders = {} }
  for k, v in pairs(opts.params or {}) do
    w.params[k] = v -- values stored before the applet runs (add_param keeps them)
  end
  local env = setmetatable({}, { __index = _G })
  env.param = {
    add_table = function(_, key, prefix, n)
      assert(w.tables[key] == nil, "table key used twice")
      w.tables[key] = { prefix = prefix, n = n }
      return true
    end,
    add_param = function(_, key, idx, name, default)
      local t = assert(w.tables[key], "add_param before add_table")
      assert(idx >= 1 and idx <= t.n, "parameter index outside the table")
      local full = t.prefix .. name
      assert(#full <= 16, "parameter name longer than 16 characters: " .. full)
      if w.params[full] == nil then
        w.params[full] = default
      end
      return true
    end,
    get = function(_, name)
      if name == "SYSID_THISMAV" then
        return w.sysid
      end
      return w.params[name]
    end,
  }
  env.mavlink = {
    init = function(_, a, b)
      assert(a >= 1 and a <= 25 and b >= 1 and b <= 25, "mavlink:init arguments outside 1..25")
      w.init = { a, b }
    end,
    register_rx_msgid = function(_, id)
      w.rx[#w.rx + 1] = id
      return true
    end,
    receive_chan = function(_)
      local m = table.remove(w.queue, 1)
      if m then
        return m, 0, w.now
      end
      return nil
    end,
  }
  env.vehicle = {
    get_mode = function(_) return w.mode end,
    set_mode = function(_, mode)
      w.set_modes[#w.set_modes + 1] = { mode = mode, t = w.now }
      if w.refuse[mode] then
        return false
      end
      w.mode = mode
      return true
    end,
  }
  env.arming = { is_armed = function(_) return w.armed end }
  env.gcs = { send_text = function(_, severity, text) w.texts[#w.texts + 1] = { sev = severity, text = text, t = w.now } end }
  env.millis = function()
    local v = w.now
    return { tofloat = function(_) return v end, toint = function(_) return math.floor(v) end }
  end
  local chunk = assert(loadfile(path, "t", env))
  w.fn, w.delay = chunk()
  assert(type(w.fn) == "function" and w.delay > 0 and w.delay <= 100, "the applet must return its update and a delay")
  w.next_call = w.delay
  return w
end

-- a sender of SET_ATTITUDE_TARGET every 20 ms and HEARTBEAT every 1000 ms, from..until (ms)
local function sender(w, s)
  s.sysid, s.compid = s.sysid or 1, s.compid or 191
  s.cmd_until, s.hb_until = s.cmd_until or math.huge, s.hb_until or math.huge
  s.last = s.from or 0
  w.senders[#w.senders + 1] = s
end

local function deliver(w)
  for _, s in ipairs(w.senders) do
    for t = s.last + 1, w.now do
      if t % 20 == 0 and t <= s.cmd_until then
        w.queue[#w.queue + 1] = message(s.sysid, s.compid, SET_ATTITUDE_TARGET)
      end
      if t % 1000 == 0 and t <= s.hb_until then
        w.queue[#w.queue + 1] = message(s.sysid, s.compid, HEARTBEAT)
      end
    end
    s.last = w.now
  end
end

-- run the scheduler until t_ms; ``at`` (ms -> function(w)) changes the world at those times
local function run(w, t_ms, at)
  at = at or {}
  while w.next_call <= t_ms do
    for t, f in pairs(at) do
      if t <= w.next_call then
        f(w)
        at[t] = nil
      end
    end
    w.now = w.next_call
    deliver(w)
    w.fn, w.delay = w.fn()
    w.next_call = w.now + w.delay
  end
end

local function critical(w)
  local out = {}
  for _, t in ipairs(w.texts) do
    if t.sev == CRITICAL then
      out[#out + 1] = t
    end
  end
  return out
end

local scenarios = {}
local function scenario(name, f)
  scenarios[#scenarios + 1] = { name = name, f = f }
end

scenario("declares FHW_ENABLE, FHW_TIMEOUT, FHW_MODE and listens to HEARTBEAT and SET_ATTITUDE_TARGET", function()
  local w = world()
  assert(w.params.FHW_ENABLE == 1 and w.params.FHW_TIMEOUT == 1.0 and w.params.FHW_MODE == LAND)
  assert(#w.rx == 2 and w.rx[1] == HEARTBEAT and w.rx[2] == SET_ATTITUDE_TARGET)
  assert(w.texts[1].sev == NOTICE and w.texts[1].text == "flowhold watchdog: watching GUIDED_NOGPS")
end)

scenario("no action while the companion commands", function()
  local w = world()
  sender(w, {})
  run(w, 20000)
  assert(#w.set_modes == 0 and #critical(w) == 0)
end)

scenario("killed: LAND once, after FHW_TIMEOUT, with its STATUSTEXT", function()
  local w = world()
  sender(w, { cmd_until = 5000, hb_until = 5000 })
  run(w, 5990)
  assert(#w.set_modes == 0, "acted before the timeout")
  run(w, 20000)
  assert(#w.set_modes == 1 and w.set_modes[1].mode == LAND, "one switch to LAND")
  local t = w.set_modes[1].t
  assert(t > 6000 and t <= 6050, "the first update past the timeout: " .. t)
  local c = critical(w)
  assert(#c == 1 and c[1].text == "flowhold watchdog: companion lost 1.0 s: LAND", c[1] and c[1].text)
  assert(#c[1].text <= 50)
end)

scenario("alive but not commanding: the text says so", function()
  local w = world()
  sender(w, { cmd_until = 5000 })
  run(w, 8000)
  local c = critical(w)
  assert(#w.set_modes == 1 and #c == 1 and c[1].text == "flowhold watchdog: no commands 1.0 s: LAND", c[1] and c[1].text)
end)

scenario("only in GUIDED_NOGPS and armed", function()
  for _, case in ipairs({ { mode = STABILIZE }, { mode = ALT_HOLD }, { armed = false } }) do
    local w = world(case)
    run(w, 10000) -- no companion at all
    assert(#w.set_modes == 0 and #critical(w) == 0)
  end
end)

scenario("entering GUIDED_NOGPS starts the wait: old commands do not count, old silence neither", function()
  local w = world({ mode = STABILIZE })
  sender(w, { cmd_until = 1000 })
  run(w, 3990, { [3000] = function(x) x.mode = GUIDED_NOGPS end })
  assert(#w.set_modes == 0, "acted less than FHW_TIMEOUT after entering GUIDED_NOGPS")
  run(w, 4100)
  assert(#w.set_modes == 1 and w.set_modes[1].t > 4000 and w.set_modes[1].t <= 4050)
end)

scenario("a new episode after the pilot returns to GUIDED_NOGPS", function()
  local w = world()
  run(w, 1100) -- no companion: LAND at 1 s
  assert(#w.set_modes == 1)
  run(w, 5000, { [3000] = function(x) x.mode = GUIDED_NOGPS end })
  assert(#w.set_modes == 2 and w.set_modes[2].t > 4000 and w.set_modes[2].t <= 4050)
end)

scenario("FHW_TIMEOUT and FHW_MODE are read from the parameters", function()
  local w = world({ params = { FHW_TIMEOUT = 2.5, FHW_MODE = ALT_HOLD } })
  sender(w, { cmd_until = 1000, hb_until = 1000 })
  run(w, 3450)
  assert(#w.set_modes == 0)
  run(w, 5000)
  assert(#w.set_modes == 1 and w.set_modes[1].mode == ALT_HOLD and w.set_modes[1].t <= 3550)
  assert(critical(w)[1].text == "flowhold watchdog: companion lost 2.5 s: ALT_HOLD")
end)

scenario("a mode refused: LAND instead, said; nothing more in the episode", function()
  local w = world({ params = { FHW_MODE = BRAKE }, refuse = { [BRAKE] = true } })
  run(w, 5000)
  assert(#w.set_modes == 2 and w.set_modes[1].mode == BRAKE and w.set_modes[2].mode == LAND)
  local c = critical(w)
  assert(#c == 3 and c[2].text == "flowhold watchdog: BRAKE refused" and c[3].text == "flowhold watchdog: LAND instead")
  local v = world({ refuse = { [LAND] = true } })
  run(v, 5000)
  assert(#v.set_modes == 1 and #critical(v) == 2, "LAND refused: tried once, said, not retried")
end)

scenario("FHW_ENABLE 0: nothing", function()
  local w = world({ params = { FHW_ENABLE = 0 } })
  run(w, 10000)
  assert(#w.set_modes == 0 and #critical(w) == 0)
end)

scenario("only the companion of this vehicle keeps it waiting", function()
  local w = world()
  sender(w, { compid = 190 }) -- a ground station
  sender(w, { sysid = 2 }) -- another vehicle's companion
  run(w, 1100)
  assert(#w.set_modes == 1)
end)

for _, s in ipairs(scenarios) do
  local ok, err = pcall(s.f)
  if not ok then
    io.stderr:write(string.format("FAILED: %s: %s\n", s.name, tostring(err)))
    os.exit(1)
  end
  print("ok: " .. s.name)
end
print(string.format("%d scenarios passed", #scenarios))
