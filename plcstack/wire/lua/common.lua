-- What every plcstack dissector shares: conversations, requests matched to their answers,
-- PDUs cut from a TCP stream (with reassembly), errors turned into expert info.

local function conversation(pinfo, server_ports)
    -- The key of the conversation (client and server end) and whether this packet goes to
    -- the server. The server is the end on one of our ports (registered or "Decode As");
    -- failing that, the end that received the conversation's first PDU.
    local src = tostring(pinfo.src) .. ":" .. tostring(pinfo.src_port)
    local dst = tostring(pinfo.dst) .. ":" .. tostring(pinfo.dst_port)
    local to_server
    if pinfo.match_uint ~= nil and pinfo.match_uint ~= 0 and pinfo.dst_port ~= pinfo.src_port then
        if pinfo.dst_port == pinfo.match_uint then
            to_server = true
        elseif pinfo.src_port == pinfo.match_uint then
            to_server = false
        end
    end
    if to_server == nil then
        local unordered = (src < dst) and (src .. "|" .. dst) or (dst .. "|" .. src)
        local server = server_ports[unordered]
        if server == nil then
            server = dst
            server_ports[unordered] = server
        end
        to_server = (server == dst)
    end
    if to_server then
        return src .. ">" .. dst, true
    end
    return dst .. ">" .. src, false
end

-- The fields every dissector uses to pair requests and answers, named ABBR.request_in,
-- ABBR.response_in and ABBR.time (the response time), and the note of an answer without its
-- request (a capture that began between them).
local function match_fields(abbr)
    return ProtoField.framenum(abbr .. ".request_in", "Request in frame", base.NONE,
            frametype.REQUEST),
        ProtoField.framenum(abbr .. ".response_in", "Response in frame", base.NONE,
            frametype.RESPONSE),
        ProtoField.relative_time(abbr .. ".time", "Time since request"),
        ProtoExpert.new(abbr .. ".unmatched", "Answer without a request in the capture",
            expert.group.SEQUENCE, expert.severity.NOTE)
end

local Track = {}
Track.__index = Track

function Track.new()
    return setmetatable({ pending = {}, by_pdu = {} }, Track)
end

function Track:reset()
    self.pending = {}
    self.by_pdu = {}
end

-- A request PDU: recorded on the first pass (in capture order), looked up on later ones.
function Track:request(pinfo, conv, key, info)
    local rec = self.by_pdu[key]
    if rec == nil and not pinfo.visited then
        rec = { frame = pinfo.number, time = pinfo.rel_ts, info = info }
        self.by_pdu[key] = rec
        local queue = self.pending[conv]
        if queue == nil then
            queue = { first = 1, last = 0 }
            self.pending[conv] = queue
        end
        queue.last = queue.last + 1
        queue[queue.last] = rec
    end
    return rec
end

-- The oldest request of the conversation still without an answer (what sizes the next one).
function Track:peek(conv)
    local queue = self.pending[conv]
    if queue == nil or queue.first > queue.last then
        return nil
    end
    return queue[queue.first]
end

-- An answer PDU: the oldest pending request is its request (none of these protocols has a
-- transaction id: answers come in the order of the requests).
function Track:response(pinfo, conv, key)
    local resp = self.by_pdu[key]
    if resp == nil and not pinfo.visited then
        local queue = self.pending[conv]
        local req = nil
        if queue ~= nil and queue.first <= queue.last then
            req = queue[queue.first]
            queue[queue.first] = nil
            queue.first = queue.first + 1
        end
        resp = { frame = pinfo.number, time = pinfo.rel_ts, req = req }
        if req ~= nil then
            req.response_frame = pinfo.number
        end
        self.by_pdu[key] = resp
    end
    return resp
end

local function nstime(seconds)
    if seconds < 0 then
        seconds = 0
    end
    local whole = math.floor(seconds)
    return NSTime.new(whole, math.floor((seconds - whole) * 1e9 + 0.5))
end

-- "request in", "response in" and the response time, as Wireshark's own dissectors show them.
local function show_match(tree, tvb, rec, f_request_in, f_response_in, f_time, is_response)
    if rec == nil then
        return
    end
    if is_response then
        local req = rec.req
        if req ~= nil then
            tree:add(f_request_in, tvb(0, 0), req.frame):set_generated()
            tree:add(f_time, tvb(0, 0), nstime(rec.time - req.time)):set_generated()
        end
    elseif rec.response_frame ~= nil then
        tree:add(f_response_in, tvb(0, 0), rec.response_frame):set_generated()
    end
end

-- An error raised while dissecting, as the expert info shows it: no script position, and
-- Wireshark's own "Range is out of bounds" said in the protocol's terms.
local function plain_error(message)
    local text = tostring(message):gsub("^[^:]*%.lua:%d+: ", "")
    if text:find("out of bounds", 1, true) then
        return "the frame ends before its fields do (truncated, or a length field is wrong)"
    end
    return text
end

-- Printable text for a message: other bytes as <XX>.
local function printable(text)
    return (text:gsub("[^%w%p ]", function(c)
        return string.format("<%02X>", c:byte())
    end))
end

-- Cut PDUs from ``tvb`` with ``length_of(tvb, offset, avail)``: a length, nil when more bytes
-- are needed to tell (TCP: reassembly asked for), or -1 when the length cannot be known (the
-- rest of the packet is taken). ``dissect_one(pdu_tvb, index)`` dissects one; a Lua error in it
-- becomes expert info on that PDU (``on_error(tvb, message)``), never a failed dissection.
local function cut_pdus(tvb, pinfo, stream, length_of, dissect_one, on_error)
    local total = tvb:len()
    local offset = 0
    local index = 0
    while offset < total do
        local ok, len = pcall(length_of, tvb, offset, total - offset)
        if not ok then
            len = -1
        end
        if len == nil then
            if stream then
                pinfo.desegment_offset = offset
                pinfo.desegment_len = DESEGMENT_ONE_MORE_SEGMENT
                return total
            end
            len = total - offset
        elseif len < 0 or len == 0 then
            len = total - offset
        elseif offset + len > total then
            if stream then
                pinfo.desegment_offset = offset
                pinfo.desegment_len = offset + len - total
                return total
            end
            len = total - offset
        end
        local pdu = tvb:range(offset, len):tvb()
        local done, message = pcall(dissect_one, pdu, index)
        if not done then
            on_error(pdu, plain_error(message))
        end
        offset = offset + len
        index = index + 1
    end
    return total
end

local function ports_from(text)
    -- "5000,1280-1281" -> list of port numbers (bad parts ignored)
    local ports = {}
    for part in string.gmatch(text or "", "[^,%s]+") do
        local a, b = string.match(part, "^(%d+)%-(%d+)$")
        if a ~= nil then
            for p = tonumber(a), math.min(tonumber(b), tonumber(a) + 64) do
                ports[#ports + 1] = p
            end
        elseif string.match(part, "^%d+$") then
            ports[#ports + 1] = tonumber(part)
        end
    end
    return ports
end

-- Registers ``proto`` on the ports of its preference ``name`` in ``table_name``, again after
-- every change of the preference.
local function register_ports(proto, table_name, pref_name)
    local registered = {}
    local function apply()
        local tbl = DissectorTable.get(table_name)
        for _, port in ipairs(registered) do
            tbl:remove(port, proto)
        end
        registered = ports_from(proto.prefs[pref_name])
        for _, port in ipairs(registered) do
            tbl:add(port, proto)
        end
    end
    return apply
end

local function hex(value, width)
    return string.format("%0" .. tostring(width or 2) .. "X", value) .. "H"
end
