--[[
current_sensor.lua - a current sensor for ArduPilot (Rover 4.x, Lua 5.3 scripting).

Sends the water current at the vehicle's position as two NAMED_VALUE_FLOAT messages,
CUR_U (eastward, m/s) and CUR_V (northward, m/s), PERIOD_MS apart: the names and units
that passt_mav's controller collects (shared/ARDUPILOT_ROVER.md, "Sensor values").

Two sources (SOURCE below):

* "grid" (simulation): the current is read from a binary grid file written by
  `passt-mav data export-lua FIELD.nc`, at the position from ahrs:get_location()
  and the field time  t = time_at_boot + millis()/1000  (time_at_boot is in the
  file header). Bilinear in space, linear in time; held at the first/last snapshot
  outside the file's time span (like vehicle_sim). Outside the grid, or where any
  of the surrounding cells is land/missing (NaN), nothing is sent.
* "serial" (a real sensor): lines "$CUR,<u>,<v>*hh" (NMEA-like, u/v in m/s
  east/north, optional XOR checksum hh) arrive on the first SERIALn port with
  SERIALn_PROTOCOL = 28 (Scripting); each valid line is forwarded as CUR_U/CUR_V.

Grid file (little-endian; Lua string.unpack formats in brackets):
  offset size
   0     4   magic "PCUR"                                   [c4]
   4     2   version = 1                                    [I2]
   6     2   header size in bytes (H = 128)                 [I2]
   8     2   rows, 10: cols                                 [I2 I2]
  12     4   snapshots T                                    [I4]
  16     8x4 lat_ref, lon_ref (deg), r_ref, c_ref (cells)   [d d d d]
  48     8x4 dr/dlat, dr/dlon, dc/dlat, dc/dlon (cells/deg) [d d d d]
  80     8   time_at_boot: field time (s) at vehicle boot   [d]
  88     8   t0: field time (s) of snapshot 0               [d]
  96     8   dt: seconds between snapshots (0 if T = 1)     [d]
 104    24   reserved (zero)
   H    T*2*rows*cols float32: for each snapshot k, u (m/s east) then v (m/s north),
        row-major (row 0 = south, column 0 = west); NaN = land/missing.
  Fractional cell of a position: r = r_ref + dr/dlat*(lat-lat_ref) + dr/dlon*(lon-lon_ref),
  c likewise (exact for lat/lon grids; a linearisation about the centre for metric ones).

The file is read two snapshots at a time (f:seek + f:read), so its size does not
count against the script heap (SCR_HEAP_SIZE).

The functions in table M are pure (no vehicle bindings) and are tested off-vehicle
(tests/test_lua_sensor.py, Lua 5.3 through lupa): set the global CURRENT_SENSOR_LIB
before running this chunk and it returns M instead of starting.
--]]

local SOURCE = "grid"            -- "grid" (simulation) or "serial" (a real sensor)
local PERIOD_MS = 250            -- 4 Hz
local GRID_FILES = { "scripts/current_grid.bin", "APM/scripts/current_grid.bin", "/APM/scripts/current_grid.bin" }
local SERIAL_INSTANCE = 0        -- first port with SERIALn_PROTOCOL = 28
local SERIAL_BAUD = 9600
local MAX_LINE = 120

local M = {}

local HEADER_FMT = "<c4I2I2I2I2I4ddddddddddd"
local HEADER_BYTES = 104         -- what HEADER_FMT reads; the header itself is H bytes

-- Parse the header (the first H bytes of a grid file). Returns a table or nil, error.
function M.parse_header(s)
  if type(s) ~= "string" or #s < HEADER_BYTES then
    return nil, "grid file too short for its header"
  end
  local magic, version, hsize, rows, cols, ntimes, lat_ref, lon_ref, r_ref, c_ref,
        drdlat, drdlon, dcdlat, dcdlon, t_boot, t0, dt = string.unpack(HEADER_FMT, s)
  if magic ~= "PCUR" then return nil, "not a current grid file (magic " .. magic .. ")" end
  if version ~= 1 then return nil, "grid file version " .. version .. " (this script reads 1)" end
  if rows < 2 or cols < 2 or ntimes < 1 then return nil, "grid file has no cells or no snapshots" end
  if ntimes > 1 and not (dt > 0) then return nil, "grid file dt must be > 0" end
  return {
    header = hsize, rows = rows, cols = cols, ntimes = ntimes,
    lat_ref = lat_ref, lon_ref = lon_ref, r_ref = r_ref, c_ref = c_ref,
    drdlat = drdlat, drdlon = drdlon, dcdlat = dcdlat, dcdlon = dcdlon,
    time_at_boot = t_boot, t0 = t0, dt = dt,
    block = 2 * rows * cols * 4,   -- bytes per snapshot
  }
end

-- Snapshot weights at field time t (s): k0, k1, w1 (value = (1-w1)*snap[k0] + w1*snap[k1]);
-- held at the first/last snapshot outside the span.
function M.time_weights(g, t)
  if g.ntimes == 1 then return 0, 0, 0.0 end
  local ft = (t - g.t0) / g.dt
  if ft <= 0 then return 0, 0, 0.0 end
  if ft >= g.ntimes - 1 then return g.ntimes - 1, g.ntimes - 1, 0.0 end
  local k0 = math.floor(ft)
  return k0, k0 + 1, ft - k0
end

-- a position this close (in cells, ~mm) outside the outer cell centres is on them: the
-- lat/lon map's rounding must not drop the grid's edge
local EDGE_EPS = 1e-6

local function snap(x, hi)
  if x < 0 and x > -EDGE_EPS then return 0 end
  if x > hi and x < hi + EDGE_EPS then return hi end
  return x
end

-- Fractional cell (r, c) of a position in degrees.
function M.fcell(g, lat, lon)
  local dla, dlo = lat - g.lat_ref, lon - g.lon_ref
  local r = g.r_ref + g.drdlat * dla + g.drdlon * dlo
  local c = g.c_ref + g.dcdlat * dla + g.dcdlon * dlo
  return snap(r, g.rows - 1), snap(c, g.cols - 1)
end

-- Bilinear (u, v) of one snapshot block (a string of 2*rows*cols float32) at fractional
-- cell (r, c), or nil when outside the grid or a cell with weight (> 1e-9) is NaN.
function M.bilinear(g, blk, r, c)
  local R, C = g.rows, g.cols
  if not (r >= 0 and r <= R - 1 and c >= 0 and c <= C - 1) then return nil end
  local r0 = math.min(math.floor(r), R - 2)
  local c0 = math.min(math.floor(c), C - 2)
  local wr, wc = r - r0, c - c0
  local plane = R * C * 4
  local u, v = 0.0, 0.0
  for dr = 0, 1 do
    local w_r = (dr == 0) and (1 - wr) or wr
    for dc = 0, 1 do
      local w = w_r * ((dc == 0) and (1 - wc) or wc)
      -- a weight below 1e-9 is lat/lon rounding at a node, not a neighbour that counts
      if w > 1e-9 then
        local off = ((r0 + dr) * C + (c0 + dc)) * 4 + 1
        local cu = string.unpack("<f", blk, off)
        local cv = string.unpack("<f", blk, off + plane)
        -- NaN ~= NaN: a missing neighbour that carries weight makes the sample missing
        if cu ~= cu or cv ~= cv then return nil end
        u = u + w * cu
        v = v + w * cv
      end
    end
  end
  return u, v
end

-- (u, v) in m/s at field time t (s) and lat/lon (deg), or nil. get_block(k) returns the
-- string of snapshot k (0-based) or nil.
function M.sample(g, get_block, t, lat, lon)
  local r, c = M.fcell(g, lat, lon)
  if not (r >= 0 and r <= g.rows - 1 and c >= 0 and c <= g.cols - 1) then return nil end
  local k0, k1, w1 = M.time_weights(g, t)
  local b0 = get_block(k0)
  if not b0 then return nil end
  local u0, v0 = M.bilinear(g, b0, r, c)
  if u0 == nil then return nil end
  if w1 <= 0 then return u0, v0 end
  local b1 = get_block(k1)
  if not b1 then return nil end
  local u1, v1 = M.bilinear(g, b1, r, c)
  if u1 == nil then return nil end
  return (1 - w1) * u0 + w1 * u1, (1 - w1) * v0 + w1 * v1
end

-- Open a grid file: returns a reader {g = header, get_block = fn} or nil, error. Keeps
-- the file open and caches the last two snapshot blocks.
function M.open_grid(path)
  local f = io.open(path, "rb")
  if not f then return nil, "cannot open " .. path end
  local head = f:read(HEADER_BYTES)
  local g, err = M.parse_header(head)
  if not g then f:close(); return nil, path .. ": " .. err end
  local cache = {}
  local function get_block(k)
    local b = cache[k]
    if b then return b end
    if k < 0 or k >= g.ntimes then return nil end
    if not f:seek("set", g.header + k * g.block) then return nil end
    b = f:read(g.block)
    if not b or #b ~= g.block then return nil end
    -- keep at most the two snapshots being interpolated between
    local n = 0
    for _ in pairs(cache) do n = n + 1 end
    if n >= 2 then cache = {} end
    cache[k] = b
    return b
  end
  return { g = g, get_block = get_block, file = f }
end

-- Parse one sensor line "$CUR,<u>,<v>[*hh]" (u, v in m/s east/north; hh = XOR of the
-- bytes between '$' and '*', two hex digits). Returns u, v or nil, reason.
function M.parse_cur_line(line)
  if type(line) ~= "string" then return nil, "not a string" end
  line = line:gsub("[\r\n]+$", "")
  local body, cs = line:match("^%$([^%*]*)%*(%x%x)$")
  if not body then
    body = line:match("^%$([^%*]*)$")
    if not body then return nil, "not a $ sentence" end
  end
  if cs then
    local x = 0
    for i = 1, #body do x = x ~ body:byte(i) end
    if x ~= tonumber(cs, 16) then return nil, "checksum mismatch" end
  end
  local tag, su, sv = body:match("^(%u+),([^,]*),([^,]*)$")
  if tag ~= "CUR" then return nil, "not a CUR sentence" end
  local u, v = tonumber(su), tonumber(sv)
  if u == nil or v == nil or u ~= u or v ~= v or math.abs(u) > 20 or math.abs(v) > 20 then
    return nil, "bad u/v"
  end
  return u, v
end

-- Feed received bytes (a string) into a line assembler; calls on_line(line) for each
-- complete line. Returns the leftover partial line (dropped when longer than MAX_LINE).
function M.feed_lines(buf, bytes, on_line)
  buf = buf .. bytes
  while true do
    local i = buf:find("\n", 1, true)
    if not i then break end
    on_line(buf:sub(1, i - 1))
    buf = buf:sub(i + 1)
  end
  if #buf > MAX_LINE then buf = "" end
  return buf
end

if CURRENT_SENSOR_LIB then
  return M
end

-- ---------------------------------------------------------------------------------
-- On the vehicle
-- ---------------------------------------------------------------------------------
local MAV_SEVERITY_ERROR, MAV_SEVERITY_INFO = 3, 6

local function send(u, v)
  gcs:send_named_float("CUR_U", u)
  gcs:send_named_float("CUR_V", v)
end

local reader = nil
local warned = false

local function grid_update()
  if reader == nil then
    local last_err
    for _, p in ipairs(GRID_FILES) do
      local r, err = M.open_grid(p)
      if r then reader = r; break end
      last_err = err
    end
    if reader == nil then
      if not warned then
        gcs:send_text(MAV_SEVERITY_ERROR, "current_sensor: no grid file (" .. tostring(last_err) .. ")")
        warned = true
      end
      return grid_update, 5000   -- the file may be copied in later
    end
    local g = reader.g
    gcs:send_text(MAV_SEVERITY_INFO, string.format("current_sensor: grid %dx%d, %d snapshots", g.rows, g.cols, g.ntimes))
  end
  local loc = ahrs:get_location()
  if loc then
    local g = reader.g
    local t = g.time_at_boot + millis():tofloat() * 0.001
    local u, v = M.sample(g, reader.get_block, t, loc:lat() * 1e-7, loc:lng() * 1e-7)
    if u ~= nil then send(u, v) end
  end
  return grid_update, PERIOD_MS
end

local port = nil
local linebuf = ""

local function serial_update()
  if port == nil then
    port = serial:find_serial(SERIAL_INSTANCE)
    if port == nil then
      gcs:send_text(MAV_SEVERITY_ERROR, "current_sensor: no serial port with SERIALn_PROTOCOL 28")
      return serial_update, 5000
    end
    port:begin(SERIAL_BAUD)
    port:set_flow_control(0)
  end
  local n = port:available()
  if type(n) ~= "number" then n = n:toint() end
  local chars = {}
  for _ = 1, math.min(n, 256) do
    local b = port:read()
    if b == nil or b < 0 then break end
    chars[#chars + 1] = string.char(b)
  end
  if #chars > 0 then
    linebuf = M.feed_lines(linebuf, table.concat(chars), function(line)
      local u, v = M.parse_cur_line(line)
      if u ~= nil then send(u, v) end
    end)
  end
  return serial_update, 50
end

if SOURCE == "serial" then
  return serial_update, 1000
end
return grid_update, 1000
