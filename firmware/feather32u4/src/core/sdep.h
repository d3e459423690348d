// sdep.h -- SDEP (Adafruit's SPI transport) driver for the nRF51822 and a BLE UART byte link.
//
// Owns: SDEP packet framing (4-byte header + <= 16 payload bytes; byte 0 type 0x10 command /
// 0x20 response / 0x40 alert / 0x80 error; bytes 1-2 command id LE; byte 3 bit 7 "more data",
// bits 4-0 payload length), splitting long payloads, the "not ready" (0xFE) / "no data" (0xFF)
// retries, and bounded waits for IRQ: every wait ends after STIPI_SDEP_TIMEOUT_US, so a missing
// module (e.g. under simavr) costs a bounded delay and never hangs the probe. BleUartLink adds
// the module's life cycle (reset, probe with "AT", connection polling) and the Nordic UART
// service byte stream (0x0A01 TX, 0x0A02 RX). Does not own the SPI peripheral (SpiPort).
#ifndef STIPI_CORE_SDEP_H
#define STIPI_CORE_SDEP_H

#include <stdint.h>

#include "../../config.h"
#include "hal.h"

namespace stipi {

const uint8_t kSdepCommand = 0x10;
const uint8_t kSdepResponse = 0x20;
const uint8_t kSdepAlert = 0x40;
const uint8_t kSdepError = 0x80;
const uint8_t kSdepMaxPayload = 16;
const uint8_t kSdepMoreData = 0x80;
const uint8_t kSdepNotReady = 0xFE;  // module busy: retry after a short wait
const uint8_t kSdepNoData = 0xFF;    // module has nothing to send

const uint16_t kSdepCmdInitialize = 0xBEEF;
const uint16_t kSdepCmdAtWrapper = 0x0A00;
const uint16_t kSdepCmdUartTx = 0x0A01;
const uint16_t kSdepCmdUartRx = 0x0A02;

const uint16_t kSdepErrInvalidCommand = 0x0001;
const uint16_t kSdepErrInvalidPayload = 0x0003;

enum SdepStatus : uint8_t {
  kSdepOk = 0,
  kSdepTimeout = 1,      // IRQ never rose, or the module stayed "not ready"
  kSdepErrorReply = 2,   // the module answered with an error packet (error id in last_error())
  kSdepBadPacket = 3,    // malformed reply: wrong type/command id, or length > 16
};

struct SdepPacket {
  uint8_t type;
  uint16_t id;       // command id, or error id for kSdepError
  bool more;
  uint8_t len;
  uint8_t payload[kSdepMaxPayload];
};

class SdepDriver {
 public:
  SdepDriver(SpiPort& spi, Clock& clock) : spi_(spi), clock_(clock), last_error_(0) {}

  // Send one packet (len <= 16). Retries while the module answers 0xFE, up to the timeout.
  SdepStatus send_packet(uint8_t type, uint16_t id, const uint8_t* payload, uint8_t len,
                         bool more);
  // Wait (bounded) for IRQ and read one packet.
  SdepStatus read_packet(SdepPacket& out);
  // Send a command (payload split into 16-byte packets with the more-data bit on all but the
  // last), then read its response packets until one without more-data. Up to resp_cap payload
  // bytes are stored in resp (the rest is read and discarded); *resp_len gets the stored count.
  SdepStatus command(uint16_t id, const uint8_t* payload, uint16_t len, uint8_t* resp,
                     uint8_t resp_cap, uint8_t* resp_len);
  // Read the response packets of command `id` (alert packets are skipped), as command() does.
  SdepStatus read_response(uint16_t id, uint8_t* resp, uint8_t resp_cap, uint8_t* resp_len);
  // 0xBEEF: reset the module without the RST line (no response).
  SdepStatus initialize();
  uint16_t last_error() const { return last_error_; }

 private:
  bool wait_irq();
  bool expired(uint32_t start_us) {
    return static_cast<uint32_t>(clock_.micros() - start_us) >= STIPI_SDEP_TIMEOUT_US;
  }
  SpiPort& spi_;
  Clock& clock_;
  uint16_t last_error_;
};

// The Bluefruit module as a ByteLink. Call poll() from the main loop.
class BleUartLink : public ByteLink {
 public:
  enum State : uint8_t { kReset, kBooting, kProbing, kReady, kAbsent };

  BleUartLink(SdepDriver& sdep, SpiPort& spi, Clock& clock);

  // Start the life cycle: pulse RST now (call once from setup).
  void begin();
  // Advance the life cycle, poll the connection and received bytes. Bounded time per call.
  void poll();

  bool is_open() override { return state_ == kReady && connected_; }
  int16_t read() override;
  bool write_frame(const uint8_t* data, uint8_t len) override;

  State state() const { return state_; }
  bool connected() const { return connected_; }
  uint16_t tx_failures() const { return tx_failures_; }

 private:
  bool at_command(const char* text, uint8_t* resp, uint8_t cap, uint8_t* n);
  void poll_connection();
  void poll_rx();
  SdepDriver& sdep_;
  SpiPort& spi_;
  Clock& clock_;
  State state_;
  bool connected_;
  uint8_t attempts_;
  uint32_t since_us_;
  uint32_t last_conn_poll_us_;
  uint32_t last_rx_poll_us_;
  uint16_t tx_failures_;
  bool resync_;  // a frame was cut short: send a 0x00 first so the host drops the fragment
  uint8_t rx_[STIPI_BLE_RX_FIFO];
  uint8_t rx_head_;
  uint8_t rx_count_;
};

}  // namespace stipi

#endif
