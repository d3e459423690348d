// sdep.h -- SDEP (Adafruit's SPI transport) driver for the nRF51822 and a BLE UART byte link.
//
// Owns: SDEP packet framing (4-byte header + <= 16 payload bytes; byte 0 type 0x10 command /
// 0x20 response / 0x40 alert / 0x80 error; bytes 1-2 command id LE; byte 3 bit 7 "more data",
// bits 4-0 payload length) and, in BleUartLink, a non-blocking command engine advanced from
// loop(): per Adafruit's SDEP.md ("Command Messages") all packets of a command go out back to
// back and ONE response (possibly several packets, "Response Messages") is read after the last;
// 0xFE (not ready) and 0xFF (nothing / IRQ still high after the last packet) are retried on a
// later pass, never in a wait loop. BleUartLink adds the module's life cycle (reset, boot wait,
// "ATE=0" as the boot probe, connection polling, and for as long as the probe runs: a module
// answering 0xFE is booting, not absent; an absent one is reset and probed again with a
// doubling back-off; one that restarts (echo back on) or stops answering is probed again) and
// the Nordic UART byte stream
// (0x0A01 TX from a ring of whole frames, 0x0A02 RX). Does not own the SPI peripheral.
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
const uint8_t kSdepNotReady = 0xFE;  // module busy: try again on a later pass
const uint8_t kSdepNoData = 0xFF;    // module has nothing to send (over-read)

const uint16_t kSdepCmdInitialize = 0xBEEF;
const uint16_t kSdepCmdAtWrapper = 0x0A00;
const uint16_t kSdepCmdUartTx = 0x0A01;
const uint16_t kSdepCmdUartRx = 0x0A02;

enum SdepStatus : uint8_t {
  kSdepOk = 0,
  kSdepAgain = 1,        // module not ready / nothing to read yet: retry on a later pass
  kSdepErrorReply = 2,   // the module answered with an error packet
  kSdepBadPacket = 3,    // malformed reply: wrong type, or length > 16
};

struct SdepPacket {
  uint8_t type;
  uint16_t id;  // command id, or error id for kSdepError
  bool more;
  uint8_t len;
  uint8_t payload[kSdepMaxPayload];
};

// One SPI transaction per call; nothing here waits for the module.
class SdepDriver {
 public:
  SdepDriver(SpiPort& spi, Clock& clock) : spi_(spi), clock_(clock) {}
  // Send one packet (len <= 16); kSdepAgain when the module answered 0xFE (nothing sent).
  SdepStatus send_packet(uint16_t id, const uint8_t* payload, uint8_t len, bool more);
  // Read one packet if IRQ is high; kSdepAgain when there is none yet (IRQ low, 0xFE, 0xFF).
  SdepStatus read_packet(SdepPacket& out);
  // 0xFE ("not ready": present, busy or booting) answers seen since start, wrapping.
  uint16_t not_ready_seen() const { return not_ready_; }

 private:
  void begin_transaction();
  SpiPort& spi_;
  Clock& clock_;
  uint16_t not_ready_ = 0;
};

// What STATUS reports about the BLE module (docs/protocol.md, STATUS ble_state).
enum BleHealth : uint8_t { kBleNotBuilt = 0, kBleAbsent = 1, kBleBooting = 2, kBleUp = 3 };

// The Bluefruit module as a ByteLink. Call poll() from the main loop: at most
// STIPI_SDEP_PACKETS_PER_POLL SPI transactions (~0.2 ms each) per call.
class BleUartLink : public ByteLink {
 public:
  enum State : uint8_t { kReset, kBooting, kProbing, kReady, kAbsent };

  BleUartLink(SdepDriver& sdep, SpiPort& spi, Clock& clock);

  void begin();  // pulse RST (from setup)
  void poll();

  bool is_open() override { return state_ == kReady && connected_; }
  int16_t read() override;
  // Queue a whole frame for BLE; false (nothing queued) when the TX ring has no room.
  bool write_frame(const uint8_t* data, uint8_t len) override;

  State state() const { return state_; }
  BleHealth health() const;
  // Times a module that was up restarted or stopped answering and was probed again.
  uint16_t module_resets() const { return module_resets_; }
  bool connected() const { return connected_; }
  uint16_t tx_failures() const { return tx_failures_; }  // UART TX commands the module refused
  uint32_t frames_lost() const { return frames_lost_; }  // queued frames lost that way
  // Flow control: the module's TX FIFO room as last reported (AT+BLEUARTFIFO=TX) minus what
  // was sent since; false while the module does not support the command (then TX relies on
  // the module's ERROR after 200 ms, as before).
  bool fifo_flow_control() const { return fifo_supported_; }
  uint16_t stale_answers() const { return stale_answers_; }
  uint16_t tx_queued() const { return tx_count_; }

 private:
  enum Job : uint8_t { kJobNone, kJobEcho, kJobConn, kJobRx, kJobTx, kJobFifo };
  void start_job(Job job, uint16_t id, uint16_t len);
  void start_boot(uint32_t now);
  void probe_failed(uint32_t now, bool busy);
  void module_lost();
  void step();
  void step_send(uint32_t now);
  void step_receive(uint32_t now);
  void finish(bool ok);
  void on_payload(const SdepPacket& p);
  void choose_job(uint32_t now);
  bool start_tx(bool dry_run);
  void on_fifo_reply(bool ok);
  bool drain_stale_answer();
  void drop_tx(uint16_t bytes);
  bool reply_ok() const;
  uint8_t tx_at(uint16_t i) const { return tx_[(tx_head_ + i) % STIPI_BLE_TX_RING]; }

  SdepDriver& sdep_;
  SpiPort& spi_;
  Clock& clock_;
  State state_;
  bool connected_;
  uint8_t attempts_;
  uint8_t silent_;           // commands in a row that nothing answered
  uint16_t module_resets_;
  uint16_t busy_mark_;       // sdep_.not_ready_seen() when the job started
  uint32_t since_us_;        // reset, boot start, or absent since
  uint32_t backoff_us_;      // next wait in kAbsent
  uint32_t last_fifo_poll_us_;
  uint16_t fifo_room_;       // TX FIFO bytes free, as far as we know
  bool fifo_supported_;
  uint32_t last_conn_poll_us_;
  uint32_t last_rx_poll_us_;
  uint16_t tx_failures_;
  uint16_t stale_answers_;   // answers read after their command had timed out
  uint32_t frames_lost_;
  // command in flight
  Job job_;
  Job last_job_;
  bool awaiting_;     // all packets sent, reading the response
  bool failed_;
  uint16_t job_id_;
  uint16_t job_len_;  // payload bytes of the command
  uint16_t job_sent_;
  uint32_t job_start_us_;
  const char* job_text_;
  uint8_t reply_[24];  // AT reply: the last bytes received
  uint8_t reply_len_;
  // TX ring of whole COBS frames (each ends with 0x00)
  uint8_t tx_[STIPI_BLE_TX_RING];
  uint16_t tx_head_;
  uint16_t tx_count_;
  // received bytes
  uint8_t rx_[STIPI_BLE_RX_FIFO];
  uint8_t rx_head_;
  uint8_t rx_count_;
};

}  // namespace stipi

#endif
