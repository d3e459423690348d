// fakes.cpp -- host fakes (see fakes.h) and the host side of irq_save/irq_restore.
#include "fakes.h"

#include <stdexcept>

#include "../src/core/crc16.h"
#include "../src/core/frame.h"

namespace {
int g_irq_depth = 0;
}

namespace stipi {
uint8_t irq_save() {
  ++g_irq_depth;
  return 0;
}
void irq_restore(uint8_t) { --g_irq_depth; }
}  // namespace stipi

namespace fakes {

int irq_depth() { return g_irq_depth; }

std::vector<uint8_t> reference_cobs_decode(const std::vector<uint8_t>& enc, bool* ok) {
  std::vector<uint8_t> out;
  *ok = true;
  size_t i = 0;
  while (i < enc.size()) {
    const uint8_t code = enc[i++];
    if (code == 0) {
      *ok = false;
      return out;
    }
    for (uint8_t k = 1; k < code; ++k) {
      if (i >= enc.size()) {
        *ok = false;
        return out;
      }
      out.push_back(enc[i++]);
    }
    if (code != 0xFF && i < enc.size()) out.push_back(0);
  }
  return out;
}

std::vector<HostFrame> take_frames(std::vector<uint8_t>& wire) {
  std::vector<HostFrame> frames;
  std::vector<uint8_t> cur;
  size_t consumed = 0;
  for (size_t i = 0; i < wire.size(); ++i) {
    if (wire[i] != 0) {
      cur.push_back(wire[i]);
      continue;
    }
    consumed = i + 1;
    if (cur.empty()) continue;
    bool ok = false;
    const std::vector<uint8_t> f = reference_cobs_decode(cur, &ok);
    cur.clear();
    if (!ok || f.size() < 10) throw std::runtime_error("undecodable frame from the probe");
    HostFrame h;
    h.version = f[0];
    h.type = f[1];
    h.seq = static_cast<uint16_t>(f[2] | f[3] << 8);
    h.t_us = static_cast<uint32_t>(f[4] | f[5] << 8 | f[6] << 16 | static_cast<uint32_t>(f[7]) << 24);
    h.body.assign(f.begin() + 8, f.end() - 2);
    const uint16_t crc = static_cast<uint16_t>(f[f.size() - 2] | f[f.size() - 1] << 8);
    h.crc_ok = crc == stipi::crc16(f.data(), static_cast<uint16_t>(f.size() - 2));
    frames.push_back(h);
  }
  wire.erase(wire.begin(), wire.begin() + static_cast<long>(consumed));
  return frames;
}

std::vector<uint8_t> command_wire(uint16_t seq, uint8_t cmd, const std::vector<uint8_t>& args,
                                  uint32_t t_us) {
  std::vector<uint8_t> body;
  body.push_back(cmd);
  body.insert(body.end(), args.begin(), args.end());
  uint8_t frame[stipi::kMaxFrameLen];
  const uint8_t n = stipi::encode_frame(frame, stipi::kMsgCommand, seq, t_us, body.data(),
                                        static_cast<uint8_t>(body.size()));
  uint8_t wire[stipi::kMaxWireLen];
  const uint8_t w = stipi::wire_encode(frame, n, wire);
  return std::vector<uint8_t>(wire, wire + w);
}

}  // namespace fakes
