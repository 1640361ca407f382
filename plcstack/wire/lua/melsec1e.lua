-- MELSEC A-series E71 "1E frame" (read/write to the PLC, fixed buffer, random access buffer),
-- binary and ASCII, over TCP and UDP.

local proto = Proto("melsec1e", "MELSEC A-series E71 1E frame")

local f = {
    code = ProtoField.string("melsec1e.code", "Code (binary or ASCII)"),
    command = ProtoField.uint8("melsec1e.command", "Command", base.HEX, COMMANDS),
    subheader = ProtoField.uint8("melsec1e.subheader", "Subheader", base.HEX),
    pc = ProtoField.uint8("melsec1e.pc", "PC number", base.HEX),
    timer = ProtoField.uint16("melsec1e.timer", "ACPU monitoring timer (x 250 ms)", base.DEC),
    device = ProtoField.string("melsec1e.device", "Device"),
    device_code = ProtoField.uint16("melsec1e.device_code", "Device code", base.HEX, DEVICE_NAMES),
    head = ProtoField.uint32("melsec1e.head", "Head device number", base.DEC),
    points = ProtoField.uint16("melsec1e.points", "Points", base.DEC),
    block = ProtoField.uint16("melsec1e.block", "Block number", base.DEC),
    end_code = ProtoField.uint8("melsec1e.end_code", "End code", base.HEX, END_CODES),
    fixed_end_code = ProtoField.uint8("melsec1e.fixed_end_code", "End code", base.HEX,
        FIXED_BUFFER_END_CODES),
    abnormal_code = ProtoField.uint8("melsec1e.abnormal_code", "Abnormal code", base.HEX,
        ABNORMAL_CODES),
    word = ProtoField.uint16("melsec1e.word", "Word", base.HEX),
    bit = ProtoField.bool("melsec1e.bit", "Bit"),
    state = ProtoField.uint8("melsec1e.state", "State", base.HEX),
    data = ProtoField.bytes("melsec1e.data", "Data"),
    address = ProtoField.uint32("melsec1e.address", "Start address", base.HEX),
    length = ProtoField.uint16("melsec1e.length", "Length", base.DEC),
    module = ProtoField.uint8("melsec1e.module", "Module number", base.HEX),
    cpu_model = ProtoField.uint8("melsec1e.cpu_model", "CPU model code", base.HEX, CPU_MODELS),
    fixed = ProtoField.uint8("melsec1e.fixed", "Fixed", base.HEX),
}
local unmatched
f.request_in, f.response_in, f.time, unmatched = match_fields("melsec1e")
proto.fields = f

local e = {
    malformed = ProtoExpert.new("melsec1e.malformed", "Malformed 1E frame",
        expert.group.MALFORMED, expert.severity.ERROR),
    error_code = ProtoExpert.new("melsec1e.error_code", "The E71 answered with an error",
        expert.group.RESPONSE_CODE, expert.severity.WARN),
    unsized = ProtoExpert.new("melsec1e.unsized", "Length not known: taken as the rest",
        expert.group.UNDECODED, expert.severity.NOTE),
}
e.unmatched = unmatched
proto.experts = e

proto.prefs.tcp_ports = Pref.string("TCP ports", DEFAULT_PORTS,
    "TCP ports of E71 connections (comma-separated, ranges as a-b)")
proto.prefs.udp_ports = Pref.string("UDP ports", DEFAULT_PORTS,
    "UDP ports of E71 connections (comma-separated, ranges as a-b)")
proto.prefs.code = Pref.enum("Code", 0, "Binary or ASCII (the module's switch SW2)",
    { { 1, "Automatic", 0 }, { 2, "Binary", 1 }, { 3, "ASCII", 2 } }, false)

local track = Track.new()
local servers = {}
local codes = {}     -- conversation -> true when ASCII
local monitors = {}  -- conversation -> last monitor registration {cmd, n}

function proto.init()
    track:reset()
    servers = {}
    codes = {}
    monitors = {}
end

local HEX = "^[0-9A-Fa-f]+$"

local function looks_ascii(tvb)
    if tvb:len() < 2 then
        return false
    end
    return tvb(0, 2):string():match(HEX) ~= nil
end

-- A field reader for both codes: ``num(w)`` is a w-byte field (binary: little-endian; ASCII:
-- 2w hexadecimal characters, most significant first).
local Reader = {}
Reader.__index = Reader

local function reader(tvb, ascii)
    return setmetatable({ tvb = tvb, pos = 0, ascii = ascii, unit = ascii and 2 or 1 }, Reader)
end

function Reader:left()
    return self.tvb:len() - self.pos
end

function Reader:num(w)
    if self.ascii then
        local range = self.tvb(self.pos, 2 * w)
        local text = range:string()
        if text:match(HEX) == nil then
            error("characters that are not hexadecimal digits in an ASCII field: "
                .. printable(text), 0)
        end
        self.pos = self.pos + 2 * w
        return tonumber(text, 16), range
    end
    local range = self.tvb(self.pos, w)
    self.pos = self.pos + w
    return range:le_uint(), range
end

function Reader:range_from(start)
    return self.tvb(start, self.pos - start)
end

local function device_name(code, number)
    local dev = DEVICES[code]
    if dev == nil then
        return string.format("device %04XH no. %d", code, number)
    end
    if dev[2] == 16 then
        return dev[1] .. string.format("%X", number)
    end
    return dev[1] .. tostring(number)
end

-- A device designation (binary: number 4 + code 2; ASCII: code 4 + number 8 characters).
function Reader:device(tree)
    local start = self.pos
    local code, crange, number, nrange
    if self.ascii then
        code, crange = self:num(2)
        number, nrange = self:num(4)
    else
        number, nrange = self:num(4)
        code, crange = self:num(2)
    end
    local name = device_name(code, number)
    local item = tree:add(f.device, self:range_from(start), name)
    item:add(f.device_code, crange, code)
    item:add(f.head, nrange, number)
    return code, number, name, item
end

-- An extended file register designation (binary: device + block 2; ASCII: block + device).
function Reader:xdevice(tree)
    local block, brange, code, number, name, item
    if self.ascii then
        block, brange = self:num(2)
        code, number, name, item = self:device(tree)
    else
        code, number, name, item = self:device(tree)
        block, brange = self:num(2)
    end
    item:add(f.block, brange, block)
    item:append_text(" (block " .. tostring(block) .. ")")
    return code, number, name
end

-- The point count field: 1 byte, then a fixed 00H (00H = 256).
function Reader:count(tree)
    local start = self.pos
    local low = self:num(1)
    local fixed = self:num(1)
    local n = low + 256 * fixed
    if n == 0 then
        n = 256
    end
    tree:add(f.points, self:range_from(start), n)
    return n
end

-- ``n`` bytes of data (binary: as they are; ASCII: two hexadecimal characters each).
function Reader:bytes(tree, n)
    local range = self.tvb(self.pos, n * self.unit)
    self.pos = self.pos + n * self.unit
    if not self.ascii then
        return tree:add(f.data, range)
    end
    local text = range:string()
    if text:match(HEX) == nil then
        error("characters that are not hexadecimal digits in ASCII data: " .. printable(text), 0)
    end
    -- the bytes the hexadecimal text stands for, shown from a data source of their own
    local decoded = ByteArray.new(text):tvb("ASCII data, decoded")
    return tree:add(f.data, decoded())
end

function Reader:words(tree, n, first_name)
    for i = 0, n - 1 do
        local value, range = self:num(2)
        local item = tree:add(f.word, range, value)
        if first_name ~= nil then
            item:prepend_text(first_name(i) .. ": ")
        end
    end
end

-- Bit data (00H, 02H, 08H): binary two points per byte, the first in the high nibble;
-- ASCII one character per point (a dummy 0 after an odd count).
function Reader:bits(tree, n, name_of)
    for i = 0, n - 1 do
        local range, on
        if self.ascii then
            range = self.tvb(self.pos + i, 1)
            local char = range:string()
            if char:match(HEX) == nil then
                error("bit character is not a hexadecimal digit: " .. printable(char), 0)
            end
            on = bit32.band(tonumber(char, 16), 1) == 1
        else
            range = self.tvb(self.pos + math.floor(i / 2), 1)
            local byte = range:uint()
            local nibble = (i % 2 == 0) and bit32.rshift(byte, 4) or bit32.band(byte, 0x0F)
            on = bit32.band(nibble, 1) == 1
        end
        local item = tree:add(f.bit, range, on)
        if name_of ~= nil then
            item:prepend_text(name_of(i) .. ": ")
        end
    end
    if self.ascii then
        self.pos = self.pos + n + (n % 2)
    else
        self.pos = self.pos + math.floor((n + 1) / 2)
    end
end

local function point_namer(code, number)
    local dev = DEVICES[code]
    return function(i)
        if dev == nil then
            return "point " .. tostring(i)
        end
        return device_name(code, number + i)
    end
end

-- -- requests ---------------------------------------------------------------------------------

-- Length of the request that starts at ``offset`` (spec 11.1), nil when more bytes are needed.
local function request_length(tvb, offset, avail, ascii)
    local u = ascii and 2 or 1
    if avail < u then
        return nil
    end
    local sub
    if ascii then
        local text = tvb(offset, 2):string()
        if text:match(HEX) == nil then
            return -1
        end
        sub = tonumber(text, 16)
    else
        sub = tvb(offset, 1):uint()
    end
    local rule = RULES[sub]
    if rule == nil then
        return -1 -- an undefined subheader cannot be sized (the E71 answers 50H)
    end
    local base, count_at, kind, per, packed = rule[1], rule[2], rule[3], rule[4], rule[5]
    if count_at < 0 then
        return base * u
    end
    local width = (kind == "byte") and 1 or 2
    if avail < (count_at + width) * u then
        return nil
    end
    local n
    if ascii then
        local text = tvb(offset + count_at * u, width * u):string()
        if text:match(HEX) == nil then
            return -1
        end
        if kind == "u16" then
            n = tonumber(text, 16)
        else
            n = tonumber(text:sub(1, 2), 16) + (kind == "pts" and 256 * tonumber(text:sub(3, 4), 16) or 0)
        end
    elseif kind == "u16" then
        n = tvb(offset + count_at, 2):le_uint()
    else
        n = tvb(offset + count_at, 1):uint()
        if kind == "pts" then
            n = n + 256 * tvb(offset + count_at + 1, 1):uint()
        end
    end
    if kind ~= "u16" and n == 0 then
        n = 256
    end
    local variable = packed and math.floor((n + 1) / 2) or n
    return (base + per * variable) * u
end

local function dissect_request(tvb, pinfo, tree, ascii, conv)
    local r = reader(tvb, ascii)
    local cmd, crange = r:num(1)
    local info = { cmd = cmd, n = 0 }
    tree:add(f.command, crange, cmd)
    local title = COMMANDS[cmd] or "undefined command"
    local summary = string.format("%02XH %s", cmd, title)
    if cmd >= 0x60 and cmd <= 0x62 then
        tree:add(f.fixed, select(2, r:num(1)), 0)
    else
        local pc, prange = r:num(1)
        tree:add(f.pc, prange, pc)
        local timer, trange = r:num(2)
        tree:add(f.timer, trange, timer):append_text(string.format(" (%.2f s)", timer * 0.25))
    end
    if RULES[cmd] == nil then
        tree:add_proto_expert_info(e.malformed, string.format("undefined subheader %02XH", cmd))
        return info, summary
    end
    if cmd <= 0x03 or cmd == 0x3B or cmd == 0x3C then
        local code, number, name = r:device(tree)
        local n = r:count(tree)
        info.n, info.code, info.number = n, code, number
        summary = summary .. " " .. name .. " x" .. tostring(n)
        if cmd == 0x02 then
            r:bits(tree, n, point_namer(code, number))
        elseif cmd == 0x03 or cmd == 0x3C then
            r:words(tree, n)
        end
    elseif cmd >= 0x04 and cmd <= 0x07 then
        local n = r:count(tree)
        info.n = n
        for i = 1, n do
            local code, number, name, item = r:device(tree)
            if cmd == 0x04 then
                local state, srange = r:num(1)
                item:add(f.state, srange, state)
                item:append_text(bit32.band(state, 1) == 1 and " ON" or " OFF")
            elseif cmd == 0x05 then
                local value, vrange = r:num(2)
                item:add(f.word, vrange, value)
            end
        end
        summary = summary .. " " .. tostring(n) .. " point(s)"
        if cmd == 0x06 or cmd == 0x07 then
            info.register = true
        end
    elseif cmd == 0x0E or cmd == 0x0F then
        local address, arange = r:num(3)
        tree:add(f.address, arange, address)
        local n, nrange = r:num(1)
        if n == 0 then
            n = 256
        end
        tree:add(f.length, nrange, n)
        local module, mrange = r:num(1)
        tree:add(f.module, mrange, module)
        tree:add(f.fixed, select(2, r:num(1)), 0)
        info.n = n
        summary = summary .. string.format(" module %02XH address %XH, %d bytes", module, address, n)
        if cmd == 0x0F then
            r:bytes(tree, n)
        end
    elseif cmd == 0x16 then
        local n, nrange = r:num(1)
        if n == 0 then
            n = 256
        end
        tree:add(f.length, nrange, n)
        r:bytes(tree, n)
        info.n = n
        summary = summary .. " " .. tostring(n) .. " byte(s)"
    elseif cmd == 0x17 or cmd == 0x18 then
        local code, number, name = r:xdevice(tree)
        local n = r:count(tree)
        info.n = n
        summary = summary .. " " .. name .. " x" .. tostring(n)
        if cmd == 0x18 then
            r:words(tree, n)
        end
    elseif cmd == 0x19 or cmd == 0x1A then
        local n = r:count(tree)
        info.n = n
        for i = 1, n do
            r:xdevice(tree)
            if cmd == 0x19 then
                local value, vrange = r:num(2)
                tree:add(f.word, vrange, value)
            end
        end
        summary = summary .. " " .. tostring(n) .. " point(s)"
        if cmd == 0x1A then
            info.register = true
        end
    elseif cmd == 0x60 then
        local n, nrange = r:num(2)
        tree:add(f.length, nrange, n)
        r:words(tree, n)
        summary = summary .. " " .. tostring(n) .. " word(s)"
    elseif cmd == 0x61 or cmd == 0x62 then
        local address, arange = r:num(2)
        tree:add(f.address, arange, address)
        local n, nrange = r:num(2)
        tree:add(f.length, nrange, n)
        info.n = n
        summary = summary .. string.format(" address %d, %d word(s)", address, n)
        if cmd == 0x62 then
            r:words(tree, n)
        end
    elseif OPAQUE[cmd] then
        if r:left() > 0 then
            tree:add(f.data, tvb(r.pos, r:left()))
        end
    end
    return info, summary
end

-- -- responses --------------------------------------------------------------------------------

-- Data bytes (binary) of the normal answer to ``req``; nil when not known.
local function answer_data(req, monitor)
    local c, n = req.cmd, req.n
    if c == 0x00 then
        return math.floor((n + 1) / 2)
    elseif c == 0x01 or c == 0x17 or c == 0x3B or c == 0x61 then
        return 2 * n
    elseif c == 0x08 or c == 0x09 or c == 0x1B then
        if monitor == nil then
            return nil
        end
        if c == 0x08 then
            return math.floor((monitor.n + 1) / 2)
        end
        return 2 * monitor.n
    elseif c == 0x0E then
        return n
    elseif c == 0x15 then
        return 2
    elseif c == 0x16 then
        return 1 + n
    elseif OPAQUE[c] then
        return nil
    end
    return 0
end

local function response_length(tvb, offset, avail, ascii, req, monitor)
    local u = ascii and 2 or 1
    if avail < 2 * u then
        return nil
    end
    local endcode
    if ascii then
        local text = tvb(offset + 2, 2):string()
        if text:match(HEX) == nil then
            return -1
        end
        endcode = tonumber(text, 16)
    else
        endcode = tvb(offset + 1, 1):uint()
    end
    if endcode == 0x5B then
        -- the abnormal code, then a 00H the A series sends and the Q series does not
        if avail >= 4 * u then
            local trailer = ascii and tvb(offset + 6, 2):string() or tvb(offset + 3, 1):uint()
            if trailer == "00" or trailer == 0 then
                return 4 * u
            end
        end
        return 3 * u
    end
    if endcode ~= 0 then
        return 2 * u
    end
    if req == nil then
        return -1
    end
    local data = answer_data(req, monitor)
    if data == nil then
        return -1
    end
    return (2 + data) * u
end

local function dissect_response(tvb, pinfo, tree, ascii, req, monitor)
    local r = reader(tvb, ascii)
    local sub, srange = r:num(1)
    tree:add(f.subheader, srange, sub)
    local cmd = bit32.band(sub, 0x7F)
    tree:add(f.command, srange, cmd):set_generated()
    local endcode, erange = r:num(1)
    local summary = string.format("%02XH answer", sub)
    if cmd == 0x60 then
        tree:add(f.fixed_end_code, erange, endcode)
    else
        tree:add(f.end_code, erange, endcode)
    end
    if endcode ~= 0 then
        local meaning = (cmd == 0x60 and FIXED_BUFFER_END_CODES or END_CODES)[endcode]
        summary = summary .. string.format(": end code %02XH %s", endcode, meaning or "(undocumented)")
        if endcode == 0x5B and r:left() >= r.unit then
            local abnormal, arange = r:num(1)
            tree:add(f.abnormal_code, arange, abnormal)
            summary = summary .. string.format(", abnormal code %02XH %s", abnormal,
                ABNORMAL_CODES[abnormal] or "(undocumented)")
            if r:left() >= r.unit then
                tree:add(f.fixed, select(2, r:num(1)), 0)
            end
        end
        tree:add_proto_expert_info(e.error_code, summary)
        return summary
    end
    summary = summary .. ": normal completion"
    if req == nil then
        if r:left() > 0 then
            tree:add(f.data, tvb(r.pos, r:left()))
        end
        return summary
    end
    local c, n = req.cmd, req.n
    if c == 0x00 then
        r:bits(tree, n, point_namer(req.code, req.number))
        summary = summary .. ", " .. tostring(n) .. " point(s)"
    elseif c == 0x08 and monitor ~= nil then
        r:bits(tree, monitor.n, nil)
    elseif c == 0x01 or c == 0x17 or c == 0x3B or c == 0x61 then
        local dev = DEVICES[req.code or -1]
        local namer = nil
        if c == 0x01 and dev ~= nil and not dev[3] then
            namer = point_namer(req.code, req.number)
        end
        r:words(tree, n, namer)
        summary = summary .. ", " .. tostring(n) .. " word(s)"
    elseif (c == 0x09 or c == 0x1B) and monitor ~= nil then
        r:words(tree, monitor.n, nil)
    elseif c == 0x0E then
        r:bytes(tree, n)
    elseif c == 0x15 then
        local model, mrange = r:num(1)
        tree:add(f.cpu_model, mrange, model)
        tree:add(f.fixed, select(2, r:num(1)), 0)
        summary = summary .. ", CPU " .. (CPU_MODELS[model] or string.format("model %02XH", model))
    elseif c == 0x16 then
        local len, lrange = r:num(1)
        tree:add(f.length, lrange, len == 0 and 256 or len)
        r:bytes(tree, math.floor(r:left() / r.unit))
    elseif r:left() > 0 then
        tree:add(f.data, tvb(r.pos, r:left()))
    end
    return summary
end

-- -- the dissector ----------------------------------------------------------------------------

local function is_ascii(conv, tvb)
    local pref = proto.prefs.code
    if pref == 1 then
        return false
    elseif pref == 2 then
        return true
    end
    local known = codes[conv]
    if known == nil then
        known = looks_ascii(tvb)
        codes[conv] = known
    end
    return known
end

function proto.dissector(tvb, pinfo, tree)
    if tvb:len() == 0 then
        return 0
    end
    local conv, to_server = conversation(pinfo, servers)
    local ascii = is_ascii(conv, tvb)
    local stream = pinfo.port_type == 2 -- TCP (udp: 3)
    pinfo.cols.protocol = "MELSEC 1E"
    local summaries = {}

    local function length_of(t, offset, avail)
        if to_server then
            return request_length(t, offset, avail, ascii)
        end
        local req = track:peek(conv)
        return response_length(t, offset, avail, ascii, req and req.info, req and req.monitor)
    end

    local function dissect_one(pdu, index)
        local key = tostring(pinfo.number) .. ":" .. tostring(index) .. (to_server and "q" or "r")
        local item = tree:add(proto, pdu)
        item:add(f.code, pdu(0, 0), ascii and "ASCII" or "binary"):set_generated()
        if to_server then
            local info, summary = dissect_request(pdu, pinfo, item, ascii, conv)
            local rec = track:request(pinfo, conv, key, info)
            if rec ~= nil and rec.info.register and not pinfo.visited then
                monitors[conv] = { cmd = rec.info.cmd, n = rec.info.n }
            end
            if rec ~= nil and not pinfo.visited then
                rec.monitor = monitors[conv]
            end
            show_match(item, pdu, rec, f.request_in, f.response_in, f.time, false)
            summaries[#summaries + 1] = summary
            item:append_text(", " .. summary)
        else
            local resp = track:response(pinfo, conv, key)
            local req = resp and resp.req
            if req == nil then
                item:add_proto_expert_info(e.unmatched)
            end
            local summary = dissect_response(pdu, pinfo, item, ascii, req and req.info,
                req and req.monitor)
            show_match(item, pdu, resp, f.request_in, f.response_in, f.time, true)
            summaries[#summaries + 1] = summary
            item:append_text(", " .. summary)
        end
    end

    local function on_error(pdu, message)
        local item = tree:add(proto, pdu)
        item:add_proto_expert_info(e.malformed, message)
        summaries[#summaries + 1] = "malformed"
    end

    local consumed = cut_pdus(tvb, pinfo, stream, length_of, dissect_one, on_error)
    if #summaries > 0 then
        pinfo.cols.info = table.concat(summaries, "; ")
    end
    return consumed
end

local apply_tcp = register_ports(proto, "tcp.port", "tcp_ports")
local apply_udp = register_ports(proto, "udp.port", "udp_ports")

function proto.prefs_changed()
    apply_tcp()
    apply_udp()
end

apply_tcp()
apply_udp()
