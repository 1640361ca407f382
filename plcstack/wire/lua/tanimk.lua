-- The Tani "SPS-Header" (8 bytes 'M' 'K', length, flags, sequence) over TCP, and the
-- FETCH/WRITE messages it carries, handed to Wireshark's own Sinec H1 dissector.

local proto = Proto("tanimk", "Tani MK header (SPS-Header)")

local f = {
    magic = ProtoField.string("tanimk.magic", "Magic"),
    length = ProtoField.uint16("tanimk.length", "DataLen", base.DEC),
    flags = ProtoField.uint16("tanimk.flags", "Flags", base.HEX),
    more = ProtoField.bool("tanimk.more", "More telegrams follow", 16, nil, 0x0001),
    seq = ProtoField.uint16("tanimk.seq", "SeqNo", base.DEC),
    life_ack = ProtoField.bool("tanimk.life_ack", "Life data ack (no user data)"),
    data = ProtoField.bytes("tanimk.data", "User data"),
    message_length = ProtoField.uint32("tanimk.message_length", "Message length", base.DEC),
    telegrams = ProtoField.uint16("tanimk.telegrams", "Telegrams of the message", base.DEC),
    first_frame = ProtoField.framenum("tanimk.first_frame", "Message starts in frame"),
}
local unmatched
f.request_in, f.response_in, f.time, unmatched = match_fields("tanimk")
proto.fields = f

local e = {
    malformed = ProtoExpert.new("tanimk.malformed", "Malformed MK telegram",
        expert.group.MALFORMED, expert.severity.ERROR),
    seq = ProtoExpert.new("tanimk.seq_jump", "SeqNo is not the previous one + 1",
        expert.group.SEQUENCE, expert.severity.NOTE),
    reserved = ProtoExpert.new("tanimk.reserved_flags", "Reserved flag bits set",
        expert.group.PROTOCOL, expert.severity.NOTE),
}
e.unmatched = unmatched
proto.experts = e

proto.prefs.tcp_ports = Pref.string("TCP ports", DEFAULT_PORTS,
    "TCP ports of connections with the MK header (comma-separated)")

local HEADER = 8
local track = Track.new()
local servers = {}
local partial = {}  -- direction -> {data = ByteArray, first = frame, telegrams = n}
local messages = {} -- pdu key -> {data = ByteArray, first = frame, telegrams = n}
local last_seq = {} -- direction -> SeqNo of the last data telegram

function proto.init()
    track:reset()
    servers = {}
    partial = {}
    messages = {}
    last_seq = {}
end

local function is_mk(tvb)
    return tvb:len() >= 2 and tvb(0, 2):string() == "MK"
end

-- Hands a complete message to the Sinec H1 dissector (FETCH/WRITE's 'S5' header); anything
-- else is shown as data.
local function hand_on(message, pinfo, tree)
    local ok, taken = pcall(DissectorTable.try_heuristics, "cotp", message, pinfo, tree)
    if ok and taken then
        return true
    end
    tree:add(f.data, message())
    return false
end

local function dissect(tvb, pinfo, tree)
    local conv, to_server = conversation(pinfo, servers)
    local direction = conv .. (to_server and ">" or "<")
    pinfo.cols.protocol = "MK"
    local infos = {}
    local handed = false

    local function length_of(t, offset, avail)
        if avail < HEADER then
            return nil
        end
        if t(offset, 2):string() ~= "MK" then
            return -1
        end
        return HEADER + t(offset + 2, 2):le_uint()
    end

    local function dissect_one(pdu, index)
        local key = tostring(pinfo.number) .. ":" .. tostring(index)
        local item = tree:add(proto, pdu(0, math.min(HEADER, pdu:len())))
        if pdu:len() < HEADER or pdu(0, 2):string() ~= "MK" then
            item:add_proto_expert_info(e.malformed, "no 'MK' header")
            infos[#infos + 1] = "malformed"
            return
        end
        item:add(f.magic, pdu(0, 2))
        local length = pdu(2, 2):le_uint()
        item:add_le(f.length, pdu(2, 2))
        local flags_item = item:add_le(f.flags, pdu(4, 2))
        flags_item:add_le(f.more, pdu(4, 2))
        local flags = pdu(4, 2):le_uint()
        local more = bit32.band(flags, 1) == 1
        if bit32.band(flags, 0xFFFE) ~= 0 then
            flags_item:add_proto_expert_info(e.reserved)
        end
        local seq = pdu(6, 2):le_uint()
        item:add_le(f.seq, pdu(6, 2))
        if length == 0 then
            item:add(f.life_ack, pdu(0, 0), true):set_generated()
            item:append_text(string.format(", life data ack, SeqNo %d", seq))
            infos[#infos + 1] = string.format("life data ack (SeqNo %d)", seq)
            return
        end
        if pdu:len() < HEADER + length then
            item:add_proto_expert_info(e.malformed, "shorter than its DataLen")
        end
        item:append_text(string.format(", %d bytes, SeqNo %d%s", length, seq,
            more and ", more follow" or ""))
        local data = pdu(HEADER, pdu:len() - HEADER)
        if not pinfo.visited then
            local previous = last_seq[direction]
            if previous ~= nil and seq ~= (previous + 1) % 65536 then
                messages[key .. "seq"] = true
            end
            last_seq[direction] = seq
            local part = partial[direction]
            if part == nil then
                part = { data = ByteArray.new(), first = pinfo.number, telegrams = 0 }
                partial[direction] = part
            end
            part.data:append(data:bytes())
            part.telegrams = part.telegrams + 1
            if not more then
                messages[key] = part
                partial[direction] = nil
            end
        end
        if messages[key .. "seq"] then
            item:add_proto_expert_info(e.seq)
        end
        local message = messages[key]
        if message == nil then
            item:add(f.data, data)
            infos[#infos + 1] = string.format("SeqNo %d, %d bytes, more follow", seq, length)
            return
        end
        local reassembled
        if message.telegrams > 1 then
            reassembled = message.data:tvb("MK message")
        else
            reassembled = data:tvb()
        end
        item:add(f.message_length, pdu(0, 0), reassembled:len()):set_generated()
        if message.telegrams > 1 then
            item:add(f.telegrams, pdu(0, 0), message.telegrams):set_generated()
            item:add(f.first_frame, pdu(0, 0), message.first):set_generated()
        end
        if to_server then
            local rec = track:request(pinfo, conv, key, {})
            show_match(item, pdu, rec, f.request_in, f.response_in, f.time, false)
        else
            local resp = track:response(pinfo, conv, key)
            if resp == nil or resp.req == nil then
                item:add_proto_expert_info(e.unmatched)
            end
            show_match(item, pdu, resp, f.request_in, f.response_in, f.time, true)
        end
        infos[#infos + 1] = string.format("SeqNo %d, message of %d bytes", seq, reassembled:len())
        handed = hand_on(reassembled, pinfo, tree) or handed
    end

    local function on_error(pdu, message)
        tree:add(proto, pdu):add_proto_expert_info(e.malformed, message)
        infos[#infos + 1] = "malformed"
    end

    local consumed = cut_pdus(tvb, pinfo, true, length_of, dissect_one, on_error)
    -- the H1 dissector writes its own summary into the Info column; ours goes in front
    if #infos > 0 then
        if handed then
            pinfo.cols.info:prepend("MK " .. table.concat(infos, "; ") .. " ")
        else
            pinfo.cols.info = "MK " .. table.concat(infos, "; ")
        end
    end
    return consumed
end

function proto.dissector(tvb, pinfo, tree)
    if not is_mk(tvb) then
        return 0 -- not the MK header: let the other dissectors (Sinec H1 for raw FETCH/WRITE) try
    end
    return dissect(tvb, pinfo, tree)
end

-- Found on any port by its header: 'MK', reserved flag bits clear, and a FETCH/WRITE 'S5'
-- header or an empty life data ack behind it.
local function heuristic(tvb, pinfo, tree)
    if tvb:len() < HEADER or not is_mk(tvb) then
        return false
    end
    if bit32.band(tvb(4, 2):le_uint(), 0xFFFE) ~= 0 then
        return false
    end
    local length = tvb(2, 2):le_uint()
    if length ~= 0 and (tvb:len() < HEADER + 2 or tvb(HEADER, 2):string() ~= "S5") then
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
