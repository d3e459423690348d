// sdep.cpp -- SDEP driver and Bluefruit BLE UART link (see sdep.h).
#include "sdep.h"

#include <string.h>

namespace stipi {

namespace {
// Upper bound on response packets read for one command (1 KB, the module's buffer size).
const uint8_t kMaxResponsePackets = 64;
const uint16_t kIrqPollUs = 10;
}  // namespace

bool SdepDriver::wait_irq() {
  const uint32_t start = clock_.micros();
  while (!spi_.irq()) {
    if (expired(start)) return false;
    clock_.delay_us(kIrqPollUs);
  }
  return true;
}

SdepStatus SdepDriver::send_packet(uint8_t type, uint16_t id, const uint8_t* payload,
                                   uint8_t len, bool more) {
  if (len > kSdepMaxPayload) return kSdepBadPacket;
  const uint32_t start = clock_.micros();
  for (;;) {
    spi_.select(true);
    clock_.delay_us(STIPI_SDEP_CS_SETUP_US);
    if (spi_.transfer(type) != kSdepNotReady) break;
    spi_.select(false);
    if (expired(start)) return kSdepTimeout;
    clock_.delay_us(STIPI_SDEP_RETRY_DELAY_US);
  }
  spi_.transfer(static_cast<uint8_t>(id));
  spi_.transfer(static_cast<uint8_t>(id >> 8));
  spi_.transfer(static_cast<uint8_t>(len | (more ? kSdepMoreData : 0)));
  for (uint8_t i = 0; i < len; ++i) spi_.transfer(payload[i]);
  spi_.select(false);
  return kSdepOk;
}

SdepStatus SdepDriver::read_packet(SdepPacket& out) {
  if (!wait_irq()) return kSdepTimeout;
  const uint32_t start = clock_.micros();
  uint8_t type;
  for (;;) {
    spi_.select(true);
    clock_.delay_us(STIPI_SDEP_CS_SETUP_US);
    type = spi_.transfer(kSdepNoData);
    if (type != kSdepNotReady && type != kSdepNoData) break;
    spi_.select(false);
    if (expired(start)) return kSdepTimeout;
    clock_.delay_us(STIPI_SDEP_RETRY_DELAY_US);
  }
  const uint8_t b1 = spi_.transfer(kSdepNoData);
  const uint8_t b2 = spi_.transfer(kSdepNoData);
  const uint8_t b3 = spi_.transfer(kSdepNoData);
  out.type = type;
  out.id = static_cast<uint16_t>(b1 | (static_cast<uint16_t>(b2) << 8));
  out.more = (b3 & kSdepMoreData) != 0;
  out.len = static_cast<uint8_t>(b3 & 0x1F);
  if (type == kSdepError) {
    spi_.select(false);
    out.len = 0;
    out.more = false;
    last_error_ = out.id;
    return kSdepErrorReply;
  }
  if ((type != kSdepResponse && type != kSdepAlert) || out.len > kSdepMaxPayload) {
    spi_.select(false);
    return kSdepBadPacket;
  }
  for (uint8_t i = 0; i < out.len; ++i) out.payload[i] = spi_.transfer(kSdepNoData);
  spi_.select(false);
  return kSdepOk;
}

SdepStatus SdepDriver::read_response(uint16_t id, uint8_t* resp, uint8_t resp_cap,
                                     uint8_t* resp_len) {
  uint8_t stored = 0;
  if (resp_len) *resp_len = 0;
  SdepPacket p;
  for (uint8_t n = 0; n < kMaxResponsePackets; ++n) {
    const SdepStatus st = read_packet(p);
    if (st != kSdepOk) return st;
    if (p.type == kSdepAlert) continue;  // unsolicited event: not our answer
    if (p.id != id) return kSdepBadPacket;
    for (uint8_t i = 0; i < p.len && stored < resp_cap; ++i) resp[stored++] = p.payload[i];
    if (resp_len) *resp_len = stored;
    if (!p.more) return kSdepOk;
  }
  return kSdepBadPacket;
}

SdepStatus SdepDriver::command(uint16_t id, const uint8_t* payload, uint16_t len, uint8_t* resp,
                               uint8_t resp_cap, uint8_t* resp_len) {
  uint16_t off = 0;
  do {
    const uint16_t left = static_cast<uint16_t>(len - off);
    const uint8_t n = left > kSdepMaxPayload ? kSdepMaxPayload : static_cast<uint8_t>(left);
    const bool more = off + n < len;
    const SdepStatus st = send_packet(kSdepCommand, id, payload + off, n, more);
    if (st != kSdepOk) return st;
    off = static_cast<uint16_t>(off + n);
  } while (off < len);
  return read_response(id, resp, resp_cap, resp_len);
}

SdepStatus SdepDriver::initialize() {
  return send_packet(kSdepCommand, kSdepCmdInitialize, 0, 0, false);
}

// ------------------------------------------------------------------------------------------

BleUartLink::BleUartLink(SdepDriver& sdep, SpiPort& spi, Clock& clock)
    : sdep_(sdep), spi_(spi), clock_(clock), state_(kReset), connected_(false), attempts_(0),
      since_us_(0), last_conn_poll_us_(0), last_rx_poll_us_(0), tx_failures_(0), resync_(false),
      rx_head_(0), rx_count_(0) {}

void BleUartLink::begin() {
  spi_.select(false);
  spi_.reset(true);
  since_us_ = clock_.micros();
  state_ = kReset;
  connected_ = false;
  attempts_ = 0;
}

bool BleUartLink::at_command(const char* text, uint8_t* resp, uint8_t cap, uint8_t* n) {
  const SdepStatus st = sdep_.command(kSdepCmdAtWrapper, reinterpret_cast<const uint8_t*>(text),
                                      static_cast<uint16_t>(strlen(text)), resp, cap, n);
  if (st != kSdepOk) return false;
  // The Bluefruit AT layer ends a successful reply with "OK\r\n".
  return *n >= 4 && memcmp(resp + *n - 4, "OK\r\n", 4) == 0;
}

void BleUartLink::poll() {
  const uint32_t now = clock_.micros();
  switch (state_) {
    case kReset:
      if (static_cast<uint32_t>(now - since_us_) >= STIPI_BLE_RESET_PULSE_US) {
        spi_.reset(false);
        since_us_ = now;
        state_ = kBooting;
      }
      break;
    case kBooting:
      if (static_cast<uint32_t>(now - since_us_) >= STIPI_BLE_BOOT_US) state_ = kProbing;
      break;
    case kProbing: {
      uint8_t resp[16];
      uint8_t n = 0;
      if (at_command("AT", resp, sizeof(resp), &n)) {
        state_ = kReady;
        poll_connection();
      } else if (++attempts_ >= STIPI_BLE_PROBE_ATTEMPTS) {
        state_ = kAbsent;  // no module answers: the BLE link stays closed, no more SPI traffic
      }
      break;
    }
    case kReady:
      if (static_cast<uint32_t>(now - last_conn_poll_us_) >= STIPI_BLE_CONN_POLL_US) {
        poll_connection();
      }
      if (connected_ && rx_count_ == 0 &&
          static_cast<uint32_t>(now - last_rx_poll_us_) >= STIPI_BLE_RX_POLL_US) {
        poll_rx();
      }
      break;
    case kAbsent:
      break;
  }
}

void BleUartLink::poll_connection() {
  last_conn_poll_us_ = clock_.micros();
  uint8_t resp[16];
  uint8_t n = 0;
  // Reply "1\r\nOK\r\n" when a central is connected, "0\r\nOK\r\n" otherwise.
  const bool was = connected_;
  connected_ = at_command("AT+GAPGETCONN", resp, sizeof(resp), &n) && resp[0] == '1';
  if (connected_ && !was) resync_ = true;  // start a new central's stream on a frame boundary
}

void BleUartLink::poll_rx() {
  last_rx_poll_us_ = clock_.micros();
  uint8_t n = 0;
  if (sdep_.command(kSdepCmdUartRx, 0, 0, rx_, sizeof(rx_), &n) != kSdepOk) n = 0;
  rx_head_ = 0;
  rx_count_ = n;
}

int16_t BleUartLink::read() {
  if (rx_count_ == 0) return -1;
  --rx_count_;
  return rx_[rx_head_++];
}

bool BleUartLink::write_frame(const uint8_t* data, uint8_t len) {
  if (!is_open()) return false;
  uint8_t dummy[1];
  uint8_t n = 0;
  if (resync_) {
    const uint8_t zero = 0;
    if (sdep_.send_packet(kSdepCommand, kSdepCmdUartTx, &zero, 1, false) != kSdepOk ||
        sdep_.read_response(kSdepCmdUartTx, dummy, 0, &n) != kSdepOk) {
      ++tx_failures_;
      return false;
    }
    resync_ = false;
  }
  uint8_t off = 0;
  while (off < len) {
    const uint8_t left = static_cast<uint8_t>(len - off);
    const uint8_t chunk = left > kSdepMaxPayload ? kSdepMaxPayload : left;
    const bool more = off + chunk < len;
    // As Adafruit's library does, each UART TX packet is answered before the next is sent;
    // an error answer means the module's ~1 KB TX buffer is full (it replies after ~200 ms).
    if (sdep_.send_packet(kSdepCommand, kSdepCmdUartTx, data + off, chunk, more) != kSdepOk ||
        sdep_.read_response(kSdepCmdUartTx, dummy, 0, &n) != kSdepOk) {
      ++tx_failures_;
      if (off > 0) resync_ = true;  // the host holds a fragment: cut it off with a 0x00
      return false;
    }
    off = static_cast<uint8_t>(off + chunk);
  }
  return true;
}

}  // namespace stipi
