// test_vectors.cpp -- the firmware codec against the shared byte-exact vectors
// (tests/vectors/protocol_vectors.txt, also used by the Python codec). Every vector kind the
// firmware handles is checked: crc, cobs, samples/status/ack (encode), command (decode),
// command_refused (through the real command handler), invalid and stream (receiver checks).
#include <cstdio>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "../src/core/cobs.h"
#include "../src/core/crc16.h"
#include "../src/core/frame.h"
#include "../src/core/probe.h"
#include "fakes.h"
#include "runner.h"

using namespace stipi;

namespace {

struct Vector {
  int line;
  std::string name, kind;
  std::map<std::string, std::string> fields;
  std::vector<uint8_t> frame, wire;
  bool has_frame = false, has_wire = false;
};

std::vector<uint8_t> unhex(const std::string& h, bool* ok) {
  std::vector<uint8_t> out;
  *ok = h.size() % 2 == 0;
  for (size_t i = 0; *ok && i < h.size(); i += 2) {
    unsigned v = 0;
    *ok = std::sscanf(h.c_str() + i, "%2x", &v) == 1;
    out.push_back(static_cast<uint8_t>(v));
  }
  return out;
}

std::vector<Vector> load_vectors() {
  std::vector<Vector> out;
  std::ifstream in(testing::vectors_path());
  if (!in) {
    testing::report_failure(__FILE__, __LINE__,
                            "cannot open vectors file '" + testing::vectors_path() + "'");
    return out;
  }
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#') continue;
    std::vector<std::string> cols;
    std::stringstream ss(line);
    std::string col;
    while (std::getline(ss, col, '\t')) cols.push_back(col);
    if (cols.size() != 5) {
      testing::report_failure(__FILE__, __LINE__, "line " + std::to_string(n) + ": expected 5 fields");
      continue;
    }
    Vector v;
    v.line = n;
    v.name = cols[0];
    v.kind = cols[1];
    if (cols[2] != "-") {
      std::stringstream fs(cols[2]);
      std::string kv;
      while (std::getline(fs, kv, ',')) {
        const size_t eq = kv.find('=');
        if (eq != std::string::npos) v.fields[kv.substr(0, eq)] = kv.substr(eq + 1);
      }
    }
    bool ok = true;
    if (cols[3] != "-") {
      v.frame = unhex(cols[3], &ok);
      v.has_frame = true;
    }
    if (ok && cols[4] != "-") {
      v.wire = unhex(cols[4], &ok);
      v.has_wire = true;
    }
    if (!ok) {
      testing::report_failure(__FILE__, __LINE__, "line " + std::to_string(n) + ": bad hex");
      continue;
    }
    out.push_back(v);
  }
  return out;
}

const std::vector<Vector>& vectors() {
  static const std::vector<Vector> v = load_vectors();
  return v;
}

long long num(const Vector& v, const std::string& key) {
  auto it = v.fields.find(key);
  if (it == v.fields.end()) {
    testing::report_failure(__FILE__, __LINE__, v.name + ": missing field " + key);
    return 0;
  }
  return std::stoll(it->second);
}

#define VCHECK(v, cond)                                                                      \
  do {                                                                                       \
    if (!(cond))                                                                             \
      ::testing::report_failure(__FILE__, __LINE__, (v).name + " (line " +                   \
                                                        std::to_string((v).line) + "): " #cond); \
  } while (0)

std::vector<uint8_t> wire_of(const std::vector<uint8_t>& frame) {
  std::vector<uint8_t> w(frame.size() + frame.size() / 254 + 2);
  const uint16_t n = cobs_encode(frame.data(), static_cast<uint16_t>(frame.size()), w.data());
  w.resize(n);
  w.push_back(0);
  return w;
}

// The encoder's frame f[0..n) and its wire form are the vector's bytes.
void check_encoded(const Vector& v, const uint8_t* f, uint8_t n) {
  VCHECK(v, std::vector<uint8_t>(f, f + n) == v.frame);
  uint8_t w[kMaxWireLen];
  const uint8_t wn = wire_encode(f, n, w);
  VCHECK(v, std::vector<uint8_t>(w, w + wn) == v.wire);
}

// Feed a wire stream into the firmware's receiver path; collect frames and rejections.
struct Received {
  std::vector<std::vector<uint8_t>> frames;  // decoded frames that passed check_frame
  std::vector<int> reasons;                  // per rejected run: CobsDecoder result or 100+DecodeResult
};

Received receive(const std::vector<uint8_t>& wire) {
  Received r;
  CobsDecoder d;
  for (uint8_t b : wire) {
    const CobsDecoder::Result res = d.feed(b);
    if (res == CobsDecoder::kError || res == CobsDecoder::kOverlong) {
      r.reasons.push_back(res);
    } else if (res == CobsDecoder::kFrame) {
      const DecodeResult c = check_frame(d.data(), d.length());
      if (c == kDecodeOk) {
        r.frames.emplace_back(d.data(), d.data() + d.length());
      } else {
        r.reasons.push_back(100 + c);
      }
    }
  }
  return r;
}

size_t count_kind(const std::string& kind) {
  size_t n = 0;
  for (const Vector& v : vectors()) n += v.kind == kind;
  return n;
}

}  // namespace

TEST(vectors_file_is_present_and_covers_every_kind) {
  CHECK(!vectors().empty());
  for (const char* k : {"crc", "cobs", "samples", "status", "command", "ack", "command_refused",
                        "invalid", "stream"}) {
    if (count_kind(k) == 0) testing::report_failure(__FILE__, __LINE__, std::string("no vectors of kind ") + k);
  }
  for (const Vector& v : vectors()) {
    static const char* known[] = {"crc", "cobs", "samples", "status", "command", "ack",
                                  "command_refused", "invalid", "stream"};
    bool ok = false;
    for (const char* k : known) ok = ok || v.kind == k;
    VCHECK(v, ok);  // a new kind must be handled here too
  }
}

TEST(vectors_crc) {
  for (const Vector& v : vectors()) {
    if (v.kind != "crc") continue;
    VCHECK(v, crc16(v.frame.data(), static_cast<uint16_t>(v.frame.size())) == num(v, "crc"));
  }
}

TEST(vectors_cobs_encode_and_decode) {
  for (const Vector& v : vectors()) {
    if (v.kind != "cobs") continue;
    VCHECK(v, static_cast<long long>(v.frame.size()) == num(v, "len"));
    VCHECK(v, wire_of(v.frame) == v.wire);
    const Received r = receive(v.wire);
    if (v.frame.size() <= kMaxFrameLen) {
      // the firmware decoder yields the bytes (check_frame then judges them as a frame)
      CobsDecoder d;
      std::vector<uint8_t> got;
      int frames = 0;
      for (uint8_t b : v.wire) {
        if (d.feed(b) == CobsDecoder::kFrame) {
          ++frames;
          got.assign(d.data(), d.data() + d.length());
        }
      }
      VCHECK(v, frames == 1);
      VCHECK(v, got == v.frame);
    } else {
      // longer than any protocol frame: discarded without buffering
      VCHECK(v, r.frames.empty());
      VCHECK(v, r.reasons.size() == 1 && r.reasons[0] == CobsDecoder::kOverlong);
    }
  }
}

TEST(vectors_samples_encode_byte_exact) {
  for (const Vector& v : vectors()) {
    if (v.kind != "samples") continue;
    const long long count = num(v, "count");
    std::vector<uint16_t> adc;
    for (long long i = 0; i < count; ++i) adc.push_back(static_cast<uint16_t>(num(v, "adc" + std::to_string(i))));
    uint8_t f[kMaxFrameLen];
    const uint8_t n = encode_samples(f, static_cast<uint16_t>(num(v, "seq")),
                                     static_cast<uint32_t>(num(v, "t_us")),
                                     static_cast<uint32_t>(num(v, "first_index")),
                                     static_cast<uint16_t>(num(v, "period_us")), adc.data(),
                                     static_cast<uint8_t>(count));
    check_encoded(v, f, n);
  }
}

TEST(vectors_status_encode_byte_exact) {
  int health_vectors = 0;
  for (const Vector& v : vectors()) {
    if (v.kind != "status") continue;
    // The 10-byte body of probes before firmware 1.1: decoded by hosts, not sent any more.
    if (v.fields.count("ble_state") == 0) continue;
    ++health_vectors;
    StatusBody s;
    s.led_level = static_cast<uint8_t>(num(v, "led_level"));
    s.rate_hz = static_cast<uint16_t>(num(v, "rate_hz"));
    s.dropped = static_cast<uint32_t>(num(v, "dropped"));
    s.supply_mv = static_cast<uint16_t>(num(v, "supply_mv"));
    s.flags = static_cast<uint8_t>(num(v, "flags"));
    s.ble_state = static_cast<uint8_t>(num(v, "ble_state"));
    s.ble_restarts = static_cast<uint16_t>(num(v, "ble_restarts"));
    s.reset_cause = static_cast<uint8_t>(num(v, "reset_cause"));
    uint8_t f[kMaxFrameLen];
    const uint8_t n = encode_status(f, static_cast<uint16_t>(num(v, "seq")),
                                    static_cast<uint32_t>(num(v, "t_us")), s);
    check_encoded(v, f, n);
  }
  CHECK(health_vectors >= 4);
}

TEST(vectors_ack_encode_byte_exact) {
  for (const Vector& v : vectors()) {
    if (v.kind != "ack") continue;
    uint8_t r[15];
    uint8_t rn = 0;
    if (v.fields.count("proto")) {  // GET_INFO result
      r[0] = static_cast<uint8_t>(num(v, "proto"));
      r[1] = static_cast<uint8_t>(num(v, "fw_major"));
      r[2] = static_cast<uint8_t>(num(v, "fw_minor"));
      r[3] = static_cast<uint8_t>(num(v, "fw_patch"));
      put_u16(r + 4, static_cast<uint16_t>(num(v, "rate_hz")));
      r[6] = static_cast<uint8_t>(num(v, "led_level"));
      put_u16(r + 7, static_cast<uint16_t>(num(v, "zero_counts")));
      put_u32(r + 9, static_cast<uint32_t>(static_cast<int32_t>(num(v, "span_un_per_count"))));
      r[13] = static_cast<uint8_t>(num(v, "adc_bits"));
      r[14] = static_cast<uint8_t>(num(v, "batch"));
      rn = 15;
    } else if (v.fields.count("zero_counts")) {  // TARE result
      put_u16(r, static_cast<uint16_t>(num(v, "zero_counts")));
      rn = 2;
    }
    uint8_t f[kMaxFrameLen];
    const uint8_t n = encode_ack(f, static_cast<uint16_t>(num(v, "seq")),
                                 static_cast<uint32_t>(num(v, "t_us")),
                                 static_cast<uint16_t>(num(v, "ref_seq")),
                                 static_cast<uint8_t>(num(v, "cmd")),
                                 static_cast<uint8_t>(num(v, "status")), r, rn);
    check_encoded(v, f, n);
  }
}

TEST(vectors_command_decode) {
  for (const Vector& v : vectors()) {
    if (v.kind != "command") continue;
    const Received rx = receive(v.wire);
    VCHECK(v, rx.frames.size() == 1 && rx.reasons.empty());
    if (rx.frames.size() != 1) continue;
    VCHECK(v, rx.frames[0] == v.frame);
    Command c;
    VCHECK(v, decode_command(v.frame.data(), static_cast<uint8_t>(v.frame.size()), c) == kDecodeOk);
    VCHECK(v, c.seq == num(v, "seq"));
    VCHECK(v, c.t_us == static_cast<uint32_t>(num(v, "t_us")));
    VCHECK(v, c.cmd == num(v, "cmd"));
    if (v.fields.count("rate_hz")) {
      VCHECK(v, c.arg_len == 2 && get_u16(c.args) == num(v, "rate_hz"));
    } else if (v.fields.count("level")) {
      VCHECK(v, c.arg_len == 1 && c.args[0] == num(v, "level"));
    } else if (v.fields.count("span_un_per_count")) {
      VCHECK(v, c.arg_len == 6);
      VCHECK(v, get_u16(c.args) == num(v, "zero_counts"));
      VCHECK(v, static_cast<int32_t>(get_u32(c.args + 2)) == num(v, "span_un_per_count"));
    } else {
      VCHECK(v, c.arg_len == 0);
    }
  }
}

TEST(vectors_command_refused_by_the_command_handler) {
  for (const Vector& v : vectors()) {
    if (v.kind != "command_refused") continue;
    fakes::FakeClock clock(1000);
    Sampler sampler;
    fakes::FakeBoard board(clock, sampler);
    fakes::FakeEeprom eeprom;
    fakes::FakeLink link;
    Probe probe(clock, board, sampler, eeprom);
    probe.set_link(kLinkUart, &link);
    probe.begin();
    link.push(v.wire);
    probe.poll();
    const auto frames = fakes::take_frames(link.tx);
    int acks = 0;
    for (const auto& f : frames) {
      if (f.type != kMsgAck) continue;
      ++acks;
      VCHECK(v, get_u16(f.body.data()) == num(v, "seq"));
      VCHECK(v, f.body[2] == num(v, "cmd"));
      VCHECK(v, f.body[3] == num(v, "status"));
      VCHECK(v, f.body.size() == 4u);  // refusals carry no result
    }
    VCHECK(v, acks == 1);
    VCHECK(v, !board.sampling && board.led == 0 && probe.rate_hz() == STIPI_DEFAULT_RATE_HZ);
  }
}

TEST(vectors_invalid_frames_are_rejected_for_the_stated_reason) {
  for (const Vector& v : vectors()) {
    if (v.kind != "invalid") continue;
    const std::string why = v.fields.count("error") ? v.fields.at("error") : "";
    const Received rx = receive(v.wire);
    // frames of other types pass check_frame; the probe's receiver then needs a valid COMMAND
    int reason = rx.reasons.empty() ? -1 : rx.reasons[0];
    if (rx.frames.size() == 1) {
      Command c;
      reason = 100 + decode_command(rx.frames[0].data(), static_cast<uint8_t>(rx.frames[0].size()), c);
      VCHECK(v, reason != 100 + kDecodeOk);
      VCHECK(v, v.has_frame && rx.frames[0] == v.frame);
    } else {
      VCHECK(v, rx.frames.empty() && rx.reasons.size() == 1);
    }
    if (why == "length") {
      VCHECK(v, reason == CobsDecoder::kOverlong || reason == 100 + kDecodeTooShort ||
                    reason == 100 + kDecodeTooLong);
    } else if (why == "cobs") {
      VCHECK(v, reason == CobsDecoder::kError);
    } else if (why == "crc") {
      VCHECK(v, reason == 100 + kDecodeBadCrc);
    } else if (why == "version") {
      VCHECK(v, reason == 100 + kDecodeBadVersion);
    } else if (why == "type") {
      VCHECK(v, reason == 100 + kDecodeNotCommand);
    } else if (why == "body") {
      // the probe only parses COMMAND bodies; other types are refused as "not a command"
      const bool is_command = v.has_frame && v.frame.size() > 1 && v.frame[1] == kMsgCommand;
      VCHECK(v, reason == 100 + (is_command ? kDecodeBadBody : kDecodeNotCommand));
    } else {
      VCHECK(v, false);  // unknown error word
    }
    // the probe never answers an invalid frame
    fakes::FakeClock clock(1000);
    Sampler sampler;
    fakes::FakeBoard board(clock, sampler);
    fakes::FakeEeprom eeprom;
    fakes::FakeLink link;
    Probe probe(clock, board, sampler, eeprom);
    probe.set_link(kLinkUart, &link);
    probe.begin();
    probe.poll();
    link.tx.clear();
    link.push(v.wire);
    for (int i = 0; i < 4; ++i) probe.poll();
    for (const auto& f : fakes::take_frames(link.tx)) VCHECK(v, f.type != kMsgAck);
    VCHECK(v, probe.rx_errors() == 1);
  }
}

TEST(vectors_stream_resynchronisation) {
  for (const Vector& v : vectors()) {
    if (v.kind != "stream") continue;
    const Received rx = receive(v.wire);
    VCHECK(v, static_cast<long long>(rx.frames.size()) == num(v, "frames"));
    VCHECK(v, static_cast<long long>(rx.reasons.size()) == num(v, "errors"));
    for (size_t i = 0; i < rx.frames.size(); ++i) {
      VCHECK(v, get_u16(rx.frames[i].data() + 2) == num(v, "seq" + std::to_string(i)));
    }
  }
}
