-- Siemens S5 AS511 (the programming port): the DLE/STX/ACK dialogue of spec part B, on a
-- serial line (a capture's exported PDUs, direction "sent" = programming device to PLC) or
-- over TCP to a serial device server.
--
-- The dialogue is followed step by step (B.4) on the first pass through the capture, in
-- capture order; what each packet holds (steps, frames, their meaning) is kept per packet,
-- so later passes show the same. A frame that spans packets is shown, de-stuffed, in the
-- packet that ends it.

local proto = Proto("as511", "Siemens S5 AS511 programming port")

local CONTROL = {
    [0x02] = "STX", [0x03] = "ETX", [0x04] = "EOT", [0x06] = "ACK", [0x10] = "DLE",
    [0x15] = "NAK", [0x16] = "SYN", [0x12] = "DC2",
}
local DIRECTIONS = { [0] = "programming device (PG) to PLC (AG)", [1] = "PLC (AG) to PG" }

local f = {
    direction = ProtoField.uint8("as511.direction", "Direction", base.DEC, DIRECTIONS),
    step = ProtoField.uint8("as511.step", "Dialogue step", base.DEC),
    element = ProtoField.string("as511.element", "Element"),
    control = ProtoField.uint8("as511.control", "Control character", base.HEX, CONTROL),
    nak = ProtoField.bool("as511.nak", "Negative acknowledgement (DLE NAK)"),
    fn = ProtoField.uint8("as511.function", "Function code", base.HEX, FUNCTIONS),
    accept = ProtoField.uint8("as511.accept", "Accept byte", base.HEX),
    terminate = ProtoField.uint8("as511.terminate", "Terminate byte", base.HEX),
    frame = ProtoField.bytes("as511.frame", "Frame (DLE-stuffed, as on the line)"),
    params = ProtoField.bytes("as511.params", "Parameters (de-stuffed)"),
    answer = ProtoField.bytes("as511.answer", "Data frame (de-stuffed)"),
    data = ProtoField.bytes("as511.data", "Memory bytes"),
    block_type = ProtoField.uint8("as511.block_type", "Block type", base.HEX, BLOCK_TYPES),
    block_number = ProtoField.uint8("as511.block_number", "Block number", base.DEC),
    dw0 = ProtoField.uint16("as511.dw0_address", "Address of DW0", base.HEX),
    sync = ProtoField.uint16("as511.sync", "Synchronisation pattern", base.HEX),
    block_id = ProtoField.uint8("as511.block_id", "Block identifier", base.HEX),
    pg_id = ProtoField.uint8("as511.pg_id", "PG identifier", base.HEX),
    library = ProtoField.uint24("as511.library", "Library number", base.HEX),
    block_length = ProtoField.uint16("as511.block_length", "Block length (words, header included)",
        base.DEC),
    start = ProtoField.uint16("as511.start_address", "Start address", base.HEX),
    stop = ProtoField.uint16("as511.end_address", "End address (inclusive)", base.HEX),
    bytes = ProtoField.uint16("as511.byte_count", "Bytes", base.DEC),
    leading = ProtoField.bytes("as511.leading", "Leading bytes"),
    mode = ProtoField.uint8("as511.mode", "Operating mode", base.HEX, MODES),
    address = ProtoField.uint16("as511.system_address", "Address", base.HEX),
    word = ProtoField.uint16("as511.word", "Word", base.HEX),
    request_in = ProtoField.framenum("as511.request_in", "Transaction started in frame",
        base.NONE, frametype.REQUEST),
    response_in = ProtoField.framenum("as511.response_in", "Transaction ended in frame",
        base.NONE, frametype.RESPONSE),
    time = ProtoField.relative_time("as511.time", "Transaction time"),
}
proto.fields = f

local e = {
    malformed = ProtoExpert.new("as511.malformed", "Malformed AS511 frame",
        expert.group.MALFORMED, expert.severity.ERROR),
    unexpected = ProtoExpert.new("as511.unexpected", "Not what this step of the dialogue expects",
        expert.group.SEQUENCE, expert.severity.WARN),
    nak = ProtoExpert.new("as511.nak_received", "The PLC refused (DLE NAK)",
        expert.group.RESPONSE_CODE, expert.severity.WARN),
    no_direction = ProtoExpert.new("as511.no_direction", "Direction unknown (no P2P direction)",
        expert.group.UNDECODED, expert.severity.NOTE),
}
proto.experts = e

proto.prefs.tcp_ports = Pref.string("TCP ports", DEFAULT_PORTS,
    "TCP ports of serial device servers carrying AS511 (comma-separated)")

local f_interface = Field.new("frame.interface_id")

-- per line: the dialogue state; per packet: what it holds
local lines = {}
local packets = {}
local servers = {}

function proto.init()
    lines = {}
    packets = {}
    servers = {}
end

-- What follows the function code, by function: does the AG answer with a data frame?
local function has_response(fn, params)
    if fn == 0x03 or fn == 0x07 or fn == 0x09 then
        return false
    end
    if fn == 0x1E then
        return params ~= nil and #params >= 1 and (params[1] == 1 or params[1] == 2)
    end
    return true
end

local function new_line()
    return { state = "IDLE", frame = nil, stuffed = nil, dle = false, fn = nil, params = nil,
        start_frame = nil, start_time = nil, fn_frame = nil }
end

local function add_item(items, offset, length, step, kind, text, extra)
    items[#items + 1] = { offset = offset, length = length, step = step, kind = kind,
        text = text, extra = extra }
end

-- One byte of a stuffed frame: returns true at the unescaped DLE ``end_char``.
local function feed_frame(line, byte, end_char)
    if line.dle then
        line.dle = false
        if byte == 0x10 then
            line.frame[#line.frame + 1] = 0x10
            return false
        end
        if byte == end_char then
            return true
        end
        line.bad = string.format("DLE followed by %02XH inside a frame", byte)
        return true
    end
    if byte == 0x10 then
        line.dle = true
        return false
    end
    line.frame[#line.frame + 1] = byte
    return false
end

-- What a DLE pair means in the current state: step, text, next state, kind (nil: unexpected).
local function dle_pair(line, nxt, from_pg)
    local s = line.state
    if nxt == 0x06 then
        if not from_pg and s == "W_ACK1" then
            return 2, "DLE ACK: the PLC is ready", "W_FN", "control"
        elseif not from_pg and s == "W_ACK2" then
            local after = has_response(line.fn, line.params) and "W_STX2" or "W_STX3"
            return 9, "DLE ACK: the PLC accepts the parameters", after, "control"
        elseif from_pg and s == "W_ACK_A" then
            return 5, "DLE ACK", "W_ACCEPT", "control"
        elseif from_pg and s == "W_ACK_B" then
            return 7, "DLE ACK (the parameter frame follows)", "RX_PARAMS", "control"
        elseif from_pg and s == "W_ACK_C" then
            return 11, "DLE ACK (the data frame follows)", "RX_DATA", "control"
        elseif from_pg and s == "W_ACK_D" then
            return 13, "DLE ACK: data frame received", "W_STX3", "control"
        elseif from_pg and s == "W_ACK_E" then
            return 15, "DLE ACK", "W_TERM", "control"
        elseif from_pg and s == "W_ACK_F" then
            return 17, "DLE ACK: transaction complete", "IDLE", "complete"
        end
    elseif nxt == 0x15 and not from_pg then
        if s == "W_ACK1" then
            return 2, "DLE NAK: the PLC is busy", "IDLE", "nak"
        elseif s == "W_STX1" then
            return 4, "DLE NAK: the PLC refuses the function", "IDLE", "nak"
        elseif s == "W_ACK2" then
            return 9, "DLE NAK: the operation cannot be carried out", "IDLE", "nak"
        end
    end
    return nil
end

local FRAMES = {
    RX_PARAMS = { kind = "params", stop = 0x04, step = 8 },
    RX_DATA = { kind = "data", stop = 0x03, step = 12 },
    W_ACCEPT = { kind = "accept", stop = 0x03, step = 6 },
    W_TERM = { kind = "terminate", stop = 0x03, step = 16 },
}
local AFTER_FRAME = { params = "W_ACK2", data = "W_ACK_D", accept = "W_ACK_B",
    terminate = "W_ACK_F" }

local function start_frame(line, which, number)
    local spec = FRAMES[which]
    line.frame = {}
    line.dle = false
    line.frame_end = spec.stop
    line.frame_kind = spec.kind
    line.frame_step = spec.step
    line.frame_first = nil -- the packet of its first byte
end

-- Runs the dialogue over the bytes of one packet (first pass) and returns its items.
local function follow(line, bytes, from_pg, number, time)
    local items = {}
    local i = 1
    local n = #bytes

    local function on_pair(nxt, off, length)
        local step, text, next_state, kind = dle_pair(line, nxt, from_pg)
        if step == nil then
            add_item(items, off, length, nil, "unexpected",
                string.format("DLE %02XH not expected from the %s in state %s", nxt,
                    from_pg and "PG" or "PLC", line.state))
            line.state = "IDLE"
            return
        end
        add_item(items, off, length, step, kind, text,
            { start = line.start_frame, start_time = line.start_time })
        line.state = next_state
        if FRAMES[next_state] ~= nil and (next_state == "RX_PARAMS" or next_state == "RX_DATA") then
            start_frame(line, next_state, number)
        end
    end

    if line.dle_pending ~= nil and n >= 1 and line.frame == nil then
        -- the second byte of a DLE pair that began at the end of the previous packet
        local pending_from_pg = line.dle_pending
        line.dle_pending = nil
        if pending_from_pg == from_pg then
            on_pair(bytes[1], 0, 1)
            i = 2
        end
    end
    while i <= n do
        local b = bytes[i]
        local off = i - 1
        local s = line.state
        if line.frame ~= nil then
            -- inside a stuffed frame: up to its unescaped DLE end, or the end of the packet
            if line.frame_first == nil then
                line.frame_first = number
            end
            local done = false
            while i <= n and not done do
                done = feed_frame(line, bytes[i], line.frame_end)
                i = i + 1
            end
            local length = i - 1 - off
            if done then
                local payload = line.frame
                line.frame = nil
                add_item(items, off, length, line.frame_step, "frame_end", line.frame_kind,
                    { payload = payload, fn = line.fn, bad = line.bad, first = line.frame_first })
                line.bad = nil
                if line.frame_kind == "params" then
                    line.params = payload
                end
                line.state = AFTER_FRAME[line.frame_kind]
            else
                add_item(items, off, length, line.frame_step, "frame_part", line.frame_kind,
                    { first = line.frame_first })
            end
        elseif from_pg and b == 0x02 and s ~= "W_FN" then
            -- STX from the PG starts a transaction (in the middle of one, it starts anew)
            if s ~= "IDLE" then
                add_item(items, off, 0, nil, "note", "the previous transaction was abandoned")
            end
            line.state = "W_ACK1"
            line.fn = nil
            line.params = nil
            line.start_frame = number
            line.start_time = time
            add_item(items, off, 1, 1, "control", "STX: the PG asks for a transaction")
            i = i + 1
        elseif from_pg and s == "W_FN" then
            line.fn = b
            line.state = "W_STX1"
            add_item(items, off, 1, 3, "function", "function code", { fn = b })
            i = i + 1
        elseif b == 0x10 then
            if i == n then
                add_item(items, off, 1, nil, "partial", "DLE (its second byte is in the next packet)")
                line.dle_pending = from_pg
                i = i + 1
            else
                on_pair(bytes[i + 1], off, 2)
                i = i + 2
            end
        elseif not from_pg and b == 0x02 and (s == "W_STX1" or s == "W_STX2" or s == "W_STX3") then
            local step = (s == "W_STX1" and 4) or (s == "W_STX2" and 10) or 14
            line.state = (s == "W_STX1" and "W_ACK_A") or (s == "W_STX2" and "W_ACK_C") or "W_ACK_E"
            add_item(items, off, 1, step, "control", "STX")
            i = i + 1
        elseif not from_pg and (s == "W_ACCEPT" or s == "W_TERM") then
            start_frame(line, s, number) -- this byte is the frame's first: taken next round
        else
            add_item(items, off, 1, nil, "unexpected",
                string.format("%02XH not expected from the %s in state %s", b,
                    from_pg and "PG" or "PLC", s))
            i = i + 1
        end
    end
    return items
end

local function u16(payload, i)
    return payload[i] * 256 + payload[i + 1]
end

-- The meaning of a complete parameter or data frame, by function (B.7).
local function explain(tree, tvb, kind, fn, payload)
    local len = tvb:len()
    if kind == "params" then
        if (fn == 0x1A or fn == 0x1B) and len >= 1 then
            tree:add(f.block_type, tvb(0, 1))
            if len >= 2 then
                tree:add(f.block_number, tvb(1, 1))
            end
            return string.format("%s%s", BLOCK_TYPES[payload[1]] or "block type ?",
                len >= 2 and tostring(payload[2]) or "")
        elseif fn == 0x04 and len >= 4 then
            tree:add(f.start, tvb(0, 2))
            tree:add(f.stop, tvb(2, 2))
            local first, last = u16(payload, 1), u16(payload, 3)
            tree:add(f.bytes, tvb(0, 4), last - first + 1):set_generated()
            return string.format("read %04XH-%04XH", first, last)
        elseif fn == 0x03 and len >= 2 then
            tree:add(f.start, tvb(0, 2))
            if len > 2 then
                tree:add(f.data, tvb(2, len - 2))
            end
            return string.format("write %d byte(s) at %04XH", len - 2, u16(payload, 1))
        elseif fn == 0x1E and len >= 1 then
            tree:add(f.mode, tvb(0, 1))
            return MODES[payload[1]] or "mode ?"
        end
        return ""
    end
    if fn == 0x1A and len >= 13 then
        tree:add(f.leading, tvb(0, 1))
        tree:add(f.dw0, tvb(1, 2))
        tree:add(f.sync, tvb(3, 2))
        tree:add(f.block_id, tvb(5, 1))
        tree:add(f.block_number, tvb(6, 1))
        tree:add(f.pg_id, tvb(7, 1))
        tree:add(f.library, tvb(8, 3))
        tree:add(f.block_length, tvb(11, 2))
        return string.format("DW0 at %04XH, %d words", u16(payload, 2), u16(payload, 12))
    elseif fn == 0x04 and len >= 5 then
        tree:add(f.leading, tvb(0, 5))
        if len > 5 then
            tree:add(f.data, tvb(5, len - 5))
        end
        return string.format("%d byte(s)", len - 5)
    elseif fn == 0x18 and len >= 17 then
        tree:add(f.leading, tvb(0, 1))
        for idx, name in ipairs(SYSTEM_ADDRESSES) do
            local at = 1 + 2 * (idx - 1)
            if at + 2 <= len then
                tree:add(f.address, tvb(at, 2)):prepend_text(name .. ": ")
            end
        end
        return "system parameters"
    elseif fn == 0x1B and len >= 1 then
        tree:add(f.leading, tvb(0, 1))
        for at = 1, len - 2, 2 do
            tree:add(f.word, tvb(at, 2))
        end
        return string.format("%d address(es)", math.floor((len - 1) / 2))
    end
    if len > 0 then
        tree:add(f.data, tvb(0, len))
    end
    return ""
end

local function show(tvb, pinfo, tree, items, from_pg)
    local item = tree:add(proto, tvb)
    item:add(f.direction, tvb(0, 0), from_pg and 0 or 1):set_generated()
    local texts = {}
    for _, it in ipairs(items) do
        local range = tvb(it.offset, it.length)
        local sub
        local label = it.text
        if it.kind == "function" then
            sub = item:add(f.fn, range)
            label = string.format("function %02XH %s", it.extra.fn,
                FUNCTIONS[it.extra.fn] or "(unknown)")
        elseif it.kind == "frame_end" or it.kind == "frame_part" then
            sub = item:add(f.frame, range)
            local what = ({ params = "parameter frame", data = "data frame",
                accept = "accept frame", terminate = "terminate frame" })[it.text]
            if it.kind == "frame_part" then
                label = what .. " (continues)"
            else
                label = what
                if it.extra.first ~= pinfo.number then
                    label = label .. string.format(" (from frame %d)", it.extra.first)
                end
                local payload = it.extra.payload
                if it.extra.bad ~= nil then
                    sub:add_proto_expert_info(e.malformed, it.extra.bad)
                end
                if it.text == "accept" then
                    if #payload >= 1 then
                        sub:add(f.accept, range(0, 1))
                    end
                elseif it.text == "terminate" then
                    if #payload >= 1 then
                        sub:add(f.terminate, range(0, 1))
                    end
                elseif #payload > 0 then
                    local ba = ByteArray.new()
                    ba:set_size(#payload)
                    for k = 1, #payload do
                        ba:set_index(k - 1, payload[k])
                    end
                    local clear = ba:tvb(it.text == "params" and "AS511 parameters"
                        or "AS511 data")
                    local inner = sub:add(it.text == "params" and f.params or f.answer, clear())
                    local meaning = explain(inner, clear, it.text, it.extra.fn, payload)
                    if meaning ~= "" then
                        label = label .. ": " .. meaning
                    end
                elseif it.text == "params" then
                    label = label .. " (empty)"
                end
            end
        elseif it.kind == "unexpected" then
            sub = item:add(f.element, range, label)
            sub:add_proto_expert_info(e.unexpected, label)
        elseif it.kind == "nak" then
            sub = item:add(f.control, range(1, 1))
            sub:add(f.nak, range, true)
            sub:add_proto_expert_info(e.nak, label)
        elseif it.kind == "note" or it.kind == "partial" then
            sub = item:add(f.element, range, label)
        else
            sub = item:add(f.control, range(it.length > 1 and 1 or 0, 1))
        end
        if it.step ~= nil then
            sub:prepend_text(string.format("step %d: ", it.step))
            sub:add(f.step, range, it.step):set_generated()
        end
        if it.kind ~= "unexpected" and it.kind ~= "function" then
            sub:append_text(" (" .. label .. ")")
        end
        if it.kind == "complete" and it.extra.start ~= nil then
            sub:add(f.request_in, range, it.extra.start):set_generated()
            local seconds = pinfo.rel_ts - it.extra.start_time
            local whole = math.floor(seconds)
            sub:add(f.time, range, NSTime.new(whole, math.floor((seconds - whole) * 1e9 + 0.5)))
                :set_generated()
        end
        texts[#texts + 1] = (it.step and ("[" .. it.step .. "] ") or "") .. label
    end
    pinfo.cols.protocol = "AS511"
    pinfo.cols.info = (from_pg and "PG>AG " or "AG>PG ") .. table.concat(texts, ", ")
end

function proto.dissector(tvb, pinfo, tree)
    local len = tvb:len()
    if len == 0 then
        return 0
    end
    local line_key, from_pg
    if pinfo.port_type == 2 then
        local conv, to_server = conversation(pinfo, servers)
        line_key, from_pg = conv, to_server
    else
        local iface = f_interface()
        line_key = "serial:" .. (iface and tostring(iface.value) or "?")
        if pinfo.p2p_dir == 0 then
            from_pg = true
        elseif pinfo.p2p_dir == 1 then
            from_pg = false
        end
    end
    if from_pg == nil then
        local item = tree:add(proto, tvb)
        item:add_proto_expert_info(e.no_direction)
        return len
    end
    local key = tostring(pinfo.number)
    local items = packets[key]
    if items == nil and not pinfo.visited then
        local line = lines[line_key]
        if line == nil then
            line = new_line()
            lines[line_key] = line
        end
        local bytes = {}
        for k = 0, len - 1 do
            bytes[k + 1] = tvb(k, 1):uint()
        end
        items = follow(line, bytes, from_pg, pinfo.number, pinfo.rel_ts)
        packets[key] = items
    end
    if items == nil then
        return len
    end
    local ok, message = pcall(show, tvb, pinfo, tree, items, from_pg)
    if not ok then
        tree:add(proto, tvb):add_proto_expert_info(e.malformed, plain_error(message))
    end
    return len
end

local apply_tcp = register_ports(proto, "tcp.port", "tcp_ports")

function proto.prefs_changed()
    apply_tcp()
end

apply_tcp()
