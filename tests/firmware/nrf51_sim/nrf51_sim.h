/* nrf51_sim.h -- a simulated nRF51822 running Adafruit's Bluefruit SDEP firmware, SPI slave side.
 *
 * Written from the vendor's protocol description (SDEP.md in Adafruit's "BluefruitLE nRF51"
 * library, read from ../shared/reference) and hardware.md -- not from the probe firmware. Plain
 * C99 so that the same model serves the host C++ tests (the probe core and Adafruit's own
 * driver run against it) and the simavr harness (behind the simulated SPI and IRQ pin).
 *
 * Behaviour, with the SDEP.md section it follows:
 *  - "Command Messages": packets of one command arrive back to back (more-data bit on all but
 *    the last); the module reassembles them and answers ONCE, after the last packet, after a
 *    configurable processing delay (process_us, 0..20 ms).
 *  - "SDEP Packet and SPI Error Identifier": while busy (processing, booting) the first byte
 *    clocked out is 0xFE (not ready) and the transaction is ignored; reading with nothing to
 *    send clocks out 0xFF (over-read).
 *  - "IRQ Pin": IRQ is high while a whole packet waits; after the last one has been read it
 *    stays high for irq_lag_us more ("the line may stay high after reading a packet"; the
 *    vendor driver's getPacket works around it) -- a read in that window gets 0xFF.
 *    (Default 20 us. A lag that ends between the vendor's available() and read() makes its
 *    readline() store EOF as a 0xFF character -- a race in the vendor driver, seen at 60 us.)
 *  - "Response Messages": answers longer than 16 bytes are split with the more-data bit.
 *  - "Error Messages": unknown command id -> 0x80 error, id 0x0001 (Invalid Cmd ID); a malformed
 *    packet (length field over 16, or fewer bytes than it announces) -> error 0x0003 (Invalid
 *    Payload), never silently dropped.
 *  - "SDEP Data Transactions": every command gets its answer; answers the master has not read
 *    yet stay queued when a new command arrives (counted in unread_at_command), never dropped.
 *  - "SPI Bus Hardware Requirements": 100 us between CS asserted and the first byte. The SPI
 *    slave is ready cs_setup_us after CS first falls; a byte clocked earlier gets 0xFE ("not
 *    ready", "SDEP Packet and SPI Error Identifier") and the transaction is ignored (cs_early).
 *    Readiness lasts until a transaction completes, so a master that retries on 0xFE (as the
 *    vendor driver does, 50 us apart) gets through.
 *  - "Alert Messages": nrf51_sim_alert() queues a 0x40 packet (e.g. 0x0002 Battery Low).
 *  - AT layer (0x0A00): echo is on after reset until "ATE=0"; replies end "OK\r\n" or
 *    "ERROR\r\n". 0x0A01 BLE UART TX, 0x0A02 BLE UART RX (hardware.md).
 *  - hardware.md: a ~1 KB TX FIFO drained by the central (tx_per_event_b bytes every
 *    conn_interval_us); a UART TX that does not fit waits for room and answers "ERROR\r\n"
 *    after tx_full_timeout_us (200 ms) -- its bytes are then discarded, none half-queued.
 *  - connect / disconnect events from the test (AT+GAPGETCONN; a disconnect empties the FIFO);
 *    a UART TX with no central connected answers "ERROR\r\n" (nothing to send it to).
 *  - Adafruit's AT command reference, "AT+BLEUARTFIFO": the FIFOs' free bytes (0.6.7 on;
 *    no_fifo_command models an older firmware answering ERROR).
 */
#ifndef NRF51_SIM_H
#define NRF51_SIM_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define NRF51_SIM_MAX_CMD 256      /* reassembled command payload [B] */
#define NRF51_SIM_OUT_PACKETS 24   /* response packets queued */
#define NRF51_SIM_TX_FIFO 1024     /* BLE UART TX FIFO [B] (hardware.md: about 1 KB) */
#define NRF51_SIM_RX_FIFO 256      /* bytes written by the central, not yet read [B] */

/* Spec violations a test can switch on (nrf51_sim.violation, or STIPI_NRF51_VIOLATION=<name>
   in the environment at nrf51_sim_init): each one must make some test fail
   (tests/firmware/test_sim_mutations.py). */
enum nrf51_sim_violation {
  NRF51_SPEC_TRUE = 0,
  NRF51_ANSWERS_EVERY_PACKET,   /* answers each packet of a multi-packet command */
  NRF51_IRQ_HIGH_WHILE_BUSY,    /* IRQ asserted while processing, no packet ready */
  NRF51_IRQ_STUCK_HIGH,         /* IRQ always asserted */
  NRF51_IRQ_DROPS_BETWEEN_PACKETS, /* IRQ low between packets of a multi-packet answer */
  NRF51_NEVER_NOT_READY,        /* busy: 0xFF instead of 0xFE, the packet silently ignored */
  NRF51_ERRORS_AS_RESPONSES,    /* error messages sent as type 0x20 */
  NRF51_DROPS_MALFORMED,        /* malformed packets dropped without an error message */
  NRF51_DISCARDS_UNREAD,        /* a new command drops answers not read yet */
  NRF51_TX_WHILE_DISCONNECTED,  /* UART TX with no central answered OK, bytes dropped */
  NRF51_NO_CS_SETUP,            /* bytes clocked right after CS are taken */
  NRF51_NO_ALERTS,              /* nrf51_sim_alert() sends nothing */
  NRF51_VIOLATION_COUNT
};
extern const char* const nrf51_sim_violation_names[NRF51_VIOLATION_COUNT];

typedef void (*nrf51_sim_notify_fn)(void* ctx, const uint8_t* data, uint16_t len);

typedef struct nrf51_sim {
  /* ---- configuration (set after nrf51_sim_init) ---- */
  uint32_t process_us;         /* command processing time after the last packet [us] */
  uint32_t irq_lag_us;         /* IRQ stays high after the last packet was read [us] */
  uint32_t boot_us;            /* reboot time after RST or 0xBEEF [us] */
  uint32_t tx_full_timeout_us; /* UART TX waiting for FIFO room answers ERROR after [us] */
  uint32_t conn_interval_us;   /* central's connection interval [us] */
  uint16_t tx_per_event_b;     /* bytes the central takes per connection event [B] */
  uint16_t tx_fifo_cap_b;      /* <= NRF51_SIM_TX_FIFO */
  int no_fifo_command;         /* firmware before 0.6.7: AT+BLEUARTFIFO answers ERROR */
  uint32_t cs_setup_us;        /* CS asserted -> SPI slave ready [us] (SDEP.md: 100) */
  int violation;               /* enum nrf51_sim_violation, NRF51_SPEC_TRUE normally */
  nrf51_sim_notify_fn on_notify; /* bytes delivered to the central */
  void* notify_ctx;
  /* ---- state ---- */
  uint32_t now_us;
  int present, connected, echo, selected, in_reset;
  uint32_t busy_until_us;      /* 0xFE until then (processing or booting) */
  int pending;                 /* a complete command waits to be processed */
  int waiting_room;            /* UART TX waiting for FIFO room */
  uint32_t wait_since_us;
  uint32_t next_event_us;
  uint32_t irq_low_at_us;      /* stale IRQ ends */
  int irq_stale;
  int between_packets;         /* a multi-packet answer is being read (more-data seen) */
  int spis_ready;              /* CS setup done; until a transaction completes */
  int spis_pending;            /* CS fell: ready at spis_ready_at_us */
  uint32_t spis_ready_at_us;
  /* command reassembly */
  uint8_t pkt[20];
  uint8_t pkt_pos;
  uint8_t mode;                /* transaction: 0 idle, 1 command in, 2 read out, 3 ignored */
  uint16_t cmd_id;
  uint8_t cmd[NRF51_SIM_MAX_CMD];
  uint16_t cmd_len;
  int cmd_open;                /* packets with more-data seen, last one still to come */
  /* response queue */
  uint8_t out[NRF51_SIM_OUT_PACKETS][20];
  uint8_t out_head, out_count, out_pos;
  /* FIFOs */
  uint8_t tx[NRF51_SIM_TX_FIFO];
  uint16_t tx_head, tx_count;
  uint8_t rx[NRF51_SIM_RX_FIFO];
  uint16_t rx_head, rx_count;
  /* ---- statistics ---- */
  uint32_t commands, packets_in, packets_out, not_ready, overreads, tx_errors;
  uint32_t bytes_notified, cmd_errors, unread_at_command, protocol_errors, cs_early, alerts;
  uint32_t room_waits;         /* UART TX commands that had to wait for FIFO room */
} nrf51_sim;

void nrf51_sim_init(nrf51_sim* m);
/* Let simulated time run to now_us (monotonic, wrapping u32): processing, central events. */
void nrf51_sim_advance(nrf51_sim* m, uint32_t now_us);
void nrf51_sim_select(nrf51_sim* m, int active);  /* CS asserted (low) = 1 */
uint8_t nrf51_sim_xfer(nrf51_sim* m, uint8_t mosi); /* one full-duplex byte; returns MISO */
int nrf51_sim_irq(const nrf51_sim* m);
void nrf51_sim_reset(nrf51_sim* m, int asserted);   /* RST line low = 1 */
void nrf51_sim_set_connected(nrf51_sim* m, int connected);
/* The central writes to the Nordic UART RX characteristic; returns bytes accepted. */
uint16_t nrf51_sim_central_write(nrf51_sim* m, const uint8_t* data, uint16_t len);
/* "Alert Messages": queue an alert (id, payload of 0..16 bytes) for the master to read. */
void nrf51_sim_alert(nrf51_sim* m, uint16_t id, const uint8_t* payload, uint8_t len);

#ifdef __cplusplus
}
#endif

#endif
