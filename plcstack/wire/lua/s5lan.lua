-- Siemens S5-LAN-LINK: the 26-byte request/response block over TCP (spec part A).

local proto = Proto("s5lan", "Siemens S5-LAN-LINK")

local CMDS = { [0x52] = "read", [0x72] = "read", [0x57] = "write", [0x77] = "write" }
local TYPES = { [0x42] = "byte (8 bit)", [0x57] = "word (16 bit)" }

local f = {
    plc_type = ProtoField.uint8("s5lan.plc_type", "PLCType", base.HEX),
    interface = ProtoField.uint16("s5lan.interface", "Interface", base.DEC),
    plc_no = ProtoField.uint8("s5lan.plc_no", "PLCNo", base.DEC),
    header_length = ProtoField.uint8("s5lan.header_length", "HdLen", base.DEC),
    cmd = ProtoField.uint8("s5lan.cmd", "Cmd", base.HEX, CMDS),
    data_type = ProtoField.uint8("s5lan.data_type", "DataType", base.HEX, TYPES),
    area = ProtoField.uint8("s5lan.area", "DataArea", base.HEX, AREAS),
    db = ProtoField.uint16("s5lan.db", "DBNo", base.DEC),
    start = ProtoField.uint16("s5lan.start", "Start", base.DEC),
    count = ProtoField.uint16("s5lan.count", "Count", base.DEC),
    err = ProtoField.int16("s5lan.err", "Err", base.DEC, ERR_MEANINGS),
    version = ProtoField.uint16("s5lan.version", "VersionNo", base.DEC),
    user_code = ProtoField.bytes("s5lan.user_code", "UserCode"),
    reserved = ProtoField.bytes("s5lan.reserved", "Reserved"),
    address = ProtoField.string("s5lan.address", "Address"),
    data = ProtoField.bytes("s5lan.data", "Data"),
    word = ProtoField.uint16("s5lan.word", "Word", base.HEX),
}
local unmatched
f.request_in, f.response_in, f.time, unmatched = match_fields("s5lan")
proto.fields = f

local e = {
    malformed = ProtoExpert.new("s5lan.malformed", "Malformed S5-LAN-LINK block",
        expert.group.MALFORMED, expert.severity.ERROR),
    error_code = ProtoExpert.new("s5lan.error_code", "The module answered with an error",
        expert.group.RESPONSE_CODE, expert.severity.WARN),
    echo = ProtoExpert.new("s5lan.echo", "The answer does not echo the request",
        expert.group.PROTOCOL, expert.severity.WARN),
}
e.unmatched = unmatched
proto.experts = e

proto.prefs.tcp_ports = Pref.string("TCP ports", DEFAULT_PORTS,
    "TCP ports of S5-LAN modules (the module's configured S5 server port; comma-separated)")
proto.prefs.big_endian = Pref.bool("Header fields big-endian", false,
    "The header's WORD fields are little-endian (PC order) by default; some peers differ")

local HEADER = 26
local track = Track.new()
local servers = {}

function proto.init()
    track:reset()
    servers = {}
end

local function u16(tvb, offset)
    if proto.prefs.big_endian then
        return tvb(offset, 2):uint()
    end
    return tvb(offset, 2):le_uint()
end

local function header_ok(tvb)
    if tvb:len() < 8 then
        return false
    end
    local plc_type = tvb(0, 1):uint()
    return (plc_type == 0x35 or plc_type == 0x05)
        and tvb(4, 1):uint() == HEADER
        and CMDS[tvb(5, 1):uint()] ~= nil
        and TYPES[tvb(6, 1):uint()] ~= nil
        and AREAS[tvb(7, 1):uint()] ~= nil
end

local function data_bytes(tvb, offset, to_server)
    local cmd = CMDS[tvb(offset + 5, 1):uint()]
    local unit = (tvb(offset + 6, 1):uint() == 0x42) and 1 or 2
    local count = u16(tvb, offset + 12)
    if to_server then
        return cmd == "write" and count * unit or 0
    end
    local err = tvb(offset + 14, 2)
    local err_value = proto.prefs.big_endian and err:int() or err:le_int()
    return (cmd == "read" and err_value == 0) and count * unit or 0
end

local function address_of(area, data_type, db, start, count)
    local letter = printable(string.char(area))
    local unit = (data_type == 0x42) and "B" or "W"
    local text
    if letter == "D" then
        text = string.format("DB%d.DW%d", db, start)
    elseif letter == "X" then
        text = string.format("DX%d.DW%d", db, start)
    elseif letter == "T" then
        text = "T" .. tostring(start)
    elseif letter == "Z" or letter == "C" then
        text = letter .. tostring(start)
    else
        local name = ({ M = "M", E = "E", I = "I", A = "A", O = "Q" })[letter] or letter
        text = name .. unit .. tostring(start)
    end
    return text .. " x" .. tostring(count)
end

local function dissect_block(tvb, pinfo, tree, to_server)
    local item = tree:add(proto, tvb)
    local get = function(off)
        return u16(tvb, off)
    end
    local plc_type = tvb(0, 1):uint()
    item:add(f.plc_type, tvb(0, 1))
    item:add(f.interface, tvb(1, 2), get(1))
    item:add(f.plc_no, tvb(3, 1))
    item:add(f.header_length, tvb(4, 1))
    local cmd, data_type, area = tvb(5, 1):uint(), tvb(6, 1):uint(), tvb(7, 1):uint()
    item:add(f.cmd, tvb(5, 1)):append_text(" ('" .. printable(string.char(cmd)) .. "')")
    item:add(f.data_type, tvb(6, 1)):append_text(" ('" .. printable(string.char(data_type)) .. "')")
    item:add(f.area, tvb(7, 1)):append_text(" ('" .. printable(string.char(area)) .. "')")
    local db, start, count = get(8), get(10), get(12)
    item:add(f.db, tvb(8, 2), db)
    item:add(f.start, tvb(10, 2), start)
    item:add(f.count, tvb(12, 2), count)
    local err_range = tvb(14, 2)
    local err = proto.prefs.big_endian and err_range:int() or err_range:le_int()
    item:add(f.err, err_range, err)
    local version = get(16)
    item:add(f.version, tvb(16, 2), version):append_text(string.format(" (V%d.%02d)",
        math.floor(version / 100), version % 100))
    item:add(f.user_code, tvb(18, 4))
    item:add(f.reserved, tvb(22, 4))
    local address = address_of(area, data_type, db, start, count)
    item:add(f.address, tvb(7, 7), address):set_generated()
    if plc_type ~= 0x35 and plc_type ~= 0x05 then
        item:add_proto_expert_info(e.malformed, string.format("PLCType %02XH is not '5'", plc_type))
    end
    if tvb(4, 1):uint() ~= HEADER then
        item:add_proto_expert_info(e.malformed, "HdLen is not 26")
    end
    local data = tvb:len() - HEADER
    if data > 0 then
        local dtree = item:add(f.data, tvb(HEADER, data))
        if data_type == 0x57 then
            for i = 0, math.floor(data / 2) - 1 do
                -- word data travel low byte first ("PC-friendly"): the module swaps them
                dtree:add(f.word, tvb(HEADER + 2 * i, 2), tvb(HEADER + 2 * i, 2):le_uint())
            end
        end
    end
    local what = CMDS[cmd] or "?"
    local summary
    if to_server then
        summary = string.format("%s %s", what == "read" and "Read" or "Write", address)
    else
        summary = string.format("Answer to %s %s: Err %d %s", what, address, err,
            ERR_MEANINGS[err] or ("unknown error " .. tostring(err)))
        if err ~= 0 then
            item:add_proto_expert_info(e.error_code, summary)
        end
    end
    item:append_text(", " .. summary)
    return item, summary, { cmd = cmd, data_type = data_type, area = area, db = db,
        start = start, count = count, user = tvb(18, 4):bytes():tohex() }
end

local ECHOED = { "cmd", "data_type", "area", "db", "start", "count", "user" }

local function dissect(tvb, pinfo, tree)
    local conv, to_server = conversation(pinfo, servers)
    pinfo.cols.protocol = "S5-LAN"
    local summaries = {}

    local function length_of(t, offset, avail)
        if avail < HEADER then
            return nil
        end
        if not header_ok(t(offset, HEADER):tvb()) then
            return -1
        end
        return HEADER + data_bytes(t, offset, to_server)
    end

    local function dissect_one(pdu, index)
        local key = tostring(pinfo.number) .. ":" .. tostring(index)
        if pdu:len() < HEADER then
            local item = tree:add(proto, pdu)
            item:add_proto_expert_info(e.malformed, "shorter than the 26-byte block")
            summaries[#summaries + 1] = "malformed"
            return
        end
        local item, summary, fields = dissect_block(pdu, pinfo, tree, to_server)
        if to_server then
            local rec = track:request(pinfo, conv, key, fields)
            show_match(item, pdu, rec, f.request_in, f.response_in, f.time, false)
        else
            local resp = track:response(pinfo, conv, key)
            local req = resp and resp.req
            if req == nil then
                item:add_proto_expert_info(e.unmatched)
            else
                for _, name in ipairs(ECHOED) do
                    if req.info[name] ~= fields[name] and not (name == "cmd"
                            and CMDS[req.info.cmd] == CMDS[fields.cmd]) then
                        item:add_proto_expert_info(e.echo, "the answer's " .. name
                            .. " differs from the request's")
                    end
                end
            end
            show_match(item, pdu, resp, f.request_in, f.response_in, f.time, true)
        end
        summaries[#summaries + 1] = summary
    end

    local function on_error(pdu, message)
        tree:add(proto, pdu):add_proto_expert_info(e.malformed, message)
        summaries[#summaries + 1] = "malformed"
    end

    local consumed = cut_pdus(tvb, pinfo, true, length_of, dissect_one, on_error)
    if #summaries > 0 then
        pinfo.cols.info = table.concat(summaries, "; ")
    end
    return consumed
end

function proto.dissector(tvb, pinfo, tree)
    if tvb:len() == 0 then
        return 0
    end
    return dissect(tvb, pinfo, tree)
end

-- Found on any port by the start of its block: '5', interface 0, HdLen 26 and known letters.
local function heuristic(tvb, pinfo, tree)
    if tvb:len() < 8 or not header_ok(tvb) or tvb(1, 3):uint() ~= 0 then
        return false
    end
    pinfo.conversation = proto
    dissect(tvb, pinfo, tree)
    return true
end

proto:register_heuristic("tcp", heuristic)

local apply_tcp = register_ports(proto, "tcp.port", "tcp_ports")

function proto.prefs_changed()
    apply_tcp()
end

apply_tcp()
