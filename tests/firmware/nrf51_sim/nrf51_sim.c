/* nrf51_sim.c -- simulated Bluefruit nRF51822 SDEP slave (see nrf51_sim.h for what it follows). */
#include "nrf51_sim.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define T_CMD 0x10
#define T_RESP 0x20
#define T_ALERT 0x40
#define T_ERR 0x80
#define NOT_READY 0xFE /* SDEP.md "SDEP Packet and SPI Error Identifier" */
#define OVERREAD 0xFF
#define MORE 0x80

static int after(uint32_t now, uint32_t t) { return (int32_t)(now - t) >= 0; }

const char* const nrf51_sim_violation_names[NRF51_VIOLATION_COUNT] = {
    "spec_true",           "answers_every_packet",    "irq_high_while_busy",
    "irq_stuck_high",      "irq_drops_between_packets", "never_not_ready",
    "errors_as_responses", "drops_malformed",          "discards_unread",
    "tx_while_disconnected", "no_cs_setup",            "no_alerts"};

static int viol(const nrf51_sim* m, int v) { return m->violation == v; }

void nrf51_sim_init(nrf51_sim* m) {
  memset(m, 0, sizeof(*m));
  m->process_us = 2000;
  m->irq_lag_us = 20;
  m->boot_us = 1000000;
  m->tx_full_timeout_us = 200000; /* hardware.md: ERROR after 200 ms when full */
  m->conn_interval_us = 30000;
  m->tx_per_event_b = 20;
  m->tx_fifo_cap_b = NRF51_SIM_TX_FIFO;
  m->present = 1;
  m->echo = 1; /* AT echo is on after reset */
  m->cs_setup_us = 100;
  {
    const char* v = getenv("STIPI_NRF51_VIOLATION");
    int i;
    for (i = 0; v && i < NRF51_VIOLATION_COUNT; ++i)
      if (strcmp(v, nrf51_sim_violation_names[i]) == 0) m->violation = i;
  }
}

static int busy(const nrf51_sim* m) {
  return m->in_reset || m->pending || m->waiting_room || !after(m->now_us, m->busy_until_us);
}

/* "Response Messages": split `len` bytes into packets, more-data on all but the last. */
static void queue_reply(nrf51_sim* m, uint8_t type, uint16_t id, const uint8_t* d, uint16_t len) {
  uint16_t off = 0;
  do {
    uint16_t n = (uint16_t)(len - off) > 16 ? 16 : (uint16_t)(len - off);
    uint8_t* p;
    if (m->out_count == NRF51_SIM_OUT_PACKETS) return;
    p = m->out[(m->out_head + m->out_count) % NRF51_SIM_OUT_PACKETS];
    p[0] = type;
    p[1] = (uint8_t)id;
    p[2] = (uint8_t)(id >> 8);
    p[3] = (uint8_t)(n | (off + n < len ? MORE : 0));
    if (n) memcpy(p + 4, d + off, n);
    ++m->out_count;
    ++m->packets_out;
    off = (uint16_t)(off + n);
  } while (off < len);
}

static void reply_text(nrf51_sim* m, uint16_t id, const char* body) {
  uint8_t buf[NRF51_SIM_MAX_CMD + 64];
  uint16_t n = 0, bl = (uint16_t)strlen(body);
  if (m->echo && id == 0x0A00) { /* echo: the command line comes back first */
    memcpy(buf, m->cmd, m->cmd_len);
    n = m->cmd_len;
    buf[n++] = '\r';
    buf[n++] = '\n';
  }
  memcpy(buf + n, body, bl);
  queue_reply(m, T_RESP, id, buf, (uint16_t)(n + bl));
}

static void error_msg(nrf51_sim* m, uint16_t err) {
  /* "Error Messages": type 0x80, error id, reserved byte. */
  uint8_t* p;
  if (m->out_count == NRF51_SIM_OUT_PACKETS) return;
  p = m->out[(m->out_head + m->out_count) % NRF51_SIM_OUT_PACKETS];
  p[0] = viol(m, NRF51_ERRORS_AS_RESPONSES) ? T_RESP : T_ERR;
  p[1] = (uint8_t)err;
  p[2] = (uint8_t)(err >> 8);
  p[3] = 0;
  ++m->out_count;
  ++m->packets_out;
  ++m->cmd_errors;
}

static void boot(nrf51_sim* m) {
  m->busy_until_us = m->now_us + m->boot_us;
  m->pending = m->waiting_room = m->cmd_open = 0;
  m->out_count = m->out_pos = 0;
  m->tx_count = m->rx_count = 0;
  m->cmd_len = 0;
  m->echo = 1;
  m->irq_stale = 0;
}

static void at_command(nrf51_sim* m) {
  char line[NRF51_SIM_MAX_CMD + 1];
  memcpy(line, m->cmd, m->cmd_len);
  line[m->cmd_len] = 0;
  while (m->cmd_len && (line[m->cmd_len - 1] == '\r' || line[m->cmd_len - 1] == '\n'))
    line[--m->cmd_len] = 0;
  if (strcmp(line, "AT") == 0) {
    reply_text(m, 0x0A00, "OK\r\n");
  } else if (strcmp(line, "ATE=0") == 0 || strcmp(line, "ATE=1") == 0) {
    reply_text(m, 0x0A00, "OK\r\n"); /* echoed with the old setting */
    m->echo = line[4] == '1';
  } else if (strcmp(line, "AT+GAPGETCONN") == 0) {
    reply_text(m, 0x0A00, m->connected ? "1\r\nOK\r\n" : "0\r\nOK\r\n");
  } else if (strcmp(line, "ATI") == 0) {
    reply_text(m, 0x0A00, "BLEFRIEND32\r\nnRF51822 QFACA10\r\nSIM\r\n0.8.1\r\nOK\r\n");
  } else if (strncmp(line, "AT+BLEUARTFIFO", 14) == 0) {
    /* Adafruit's AT command reference, "AT+BLEUARTFIFO" (firmware 0.6.7 on): free bytes of the
       BLE UART FIFOs, "TX,RX" without a parameter, one of them with "=TX" / "=RX". */
    char out[32];
    const unsigned tx_free = (unsigned)(m->tx_fifo_cap_b - m->tx_count);
    const unsigned rx_free = (unsigned)(NRF51_SIM_RX_FIFO - m->rx_count);
    if (strcmp(line + 14, "") == 0) snprintf(out, sizeof out, "%u,%u\r\nOK\r\n", tx_free, rx_free);
    else if (strcmp(line + 14, "=TX") == 0) snprintf(out, sizeof out, "%u\r\nOK\r\n", tx_free);
    else if (strcmp(line + 14, "=RX") == 0) snprintf(out, sizeof out, "%u\r\nOK\r\n", rx_free);
    else snprintf(out, sizeof out, "ERROR\r\n");
    if (m->no_fifo_command) snprintf(out, sizeof out, "ERROR\r\n");
    reply_text(m, 0x0A00, out);
  } else if (strcmp(line, "ATZ") == 0) {
    reply_text(m, 0x0A00, "OK\r\n");
  } else {
    reply_text(m, 0x0A00, "ERROR\r\n");
  }
}

static void uart_rx(nrf51_sim* m) {
  uint8_t buf[NRF51_SIM_RX_FIFO];
  uint16_t n = m->rx_count, i;
  for (i = 0; i < n; ++i) buf[i] = m->rx[(m->rx_head + i) % NRF51_SIM_RX_FIFO];
  m->rx_head = (uint16_t)((m->rx_head + n) % NRF51_SIM_RX_FIFO);
  m->rx_count = 0;
  queue_reply(m, T_RESP, 0x0A02, buf, n);
}

/* 0x0A01: queue the whole payload if it fits, else wait for room (ERROR after the timeout). */
static int uart_tx_try(nrf51_sim* m) {
  uint16_t i;
  if (!m->connected) { /* nobody to send to */
    if (viol(m, NRF51_TX_WHILE_DISCONNECTED)) queue_reply(m, T_RESP, 0x0A01, 0, 0);
    else queue_reply(m, T_RESP, 0x0A01, (const uint8_t*)"ERROR\r\n", 7);
    return 1;
  }
  if (m->tx_count + m->cmd_len > m->tx_fifo_cap_b) return 0;
  for (i = 0; i < m->cmd_len; ++i)
    m->tx[(m->tx_head + m->tx_count + i) % NRF51_SIM_TX_FIFO] = m->cmd[i];
  m->tx_count = (uint16_t)(m->tx_count + m->cmd_len);
  queue_reply(m, T_RESP, 0x0A01, 0, 0);
  return 1;
}

static void process(nrf51_sim* m) {
  m->pending = 0;
  ++m->commands;
  switch (m->cmd_id) {
    case 0xBEEF: boot(m); break; /* initialize: reset, no response */
    case 0x0A00: at_command(m); break;
    case 0x0A02: uart_rx(m); break;
    case 0x0A01:
      if (!uart_tx_try(m)) {
        ++m->room_waits;
        m->waiting_room = 1;
        m->wait_since_us = m->now_us;
      }
      break;
    default: error_msg(m, 0x0001); break; /* Invalid Cmd ID */
  }
  if (!m->waiting_room) m->cmd_len = 0;
}

static void central_event(nrf51_sim* m) {
  uint16_t n = m->tx_count < m->tx_per_event_b ? m->tx_count : m->tx_per_event_b, i;
  uint8_t buf[NRF51_SIM_TX_FIFO];
  if (!n) return;
  for (i = 0; i < n; ++i) buf[i] = m->tx[(m->tx_head + i) % NRF51_SIM_TX_FIFO];
  m->tx_head = (uint16_t)((m->tx_head + n) % NRF51_SIM_TX_FIFO);
  m->tx_count = (uint16_t)(m->tx_count - n);
  m->bytes_notified += n;
  if (m->on_notify) m->on_notify(m->notify_ctx, buf, n);
}

static void step_room_wait(nrf51_sim* m) {
  if (!m->waiting_room) return;
  if (uart_tx_try(m)) {
    m->waiting_room = 0;
    m->cmd_len = 0;
  } else if (after(m->now_us, m->wait_since_us + m->tx_full_timeout_us)) {
    m->waiting_room = 0;
    m->cmd_len = 0;
    ++m->tx_errors;
    queue_reply(m, T_RESP, 0x0A01, (const uint8_t*)"ERROR\r\n", 7);
  }
}

void nrf51_sim_advance(nrf51_sim* m, uint32_t now_us) {
  /* Central events in order, so FIFO room appears at the right instants. */
  while (m->connected && m->conn_interval_us && after(now_us, m->next_event_us)) {
    m->now_us = m->next_event_us;
    if (m->pending && after(m->now_us, m->busy_until_us)) process(m);
    central_event(m);
    step_room_wait(m);
    m->next_event_us += m->conn_interval_us;
  }
  m->now_us = now_us;
  if (m->pending && after(now_us, m->busy_until_us)) process(m);
  step_room_wait(m);
  if (m->irq_stale && after(now_us, m->irq_low_at_us)) m->irq_stale = 0;
}

int nrf51_sim_irq(const nrf51_sim* m) {
  if (!m->present || m->in_reset) return 0;
  if (viol(m, NRF51_IRQ_STUCK_HIGH)) return 1;
  if (viol(m, NRF51_IRQ_HIGH_WHILE_BUSY) && (m->pending || m->waiting_room)) return 1;
  if (viol(m, NRF51_IRQ_DROPS_BETWEEN_PACKETS) && m->between_packets) return 0;
  return m->out_count > 0 || m->irq_stale; /* "IRQ Pin" */
}

static void end_packet_in(nrf51_sim* m) {
  const uint8_t len = (uint8_t)(m->pkt[3] & 0x1F);
  const uint16_t id = (uint16_t)(m->pkt[1] | m->pkt[2] << 8);
  if (m->pkt_pos < 4 || m->pkt_pos < 4 + len || len > 16) {
    ++m->protocol_errors; /* short or malformed packet: "Error Messages", 0x0003 */
    if (!viol(m, NRF51_DROPS_MALFORMED)) error_msg(m, 0x0003);
    return;
  }
  ++m->packets_in;
  if (!m->cmd_open) {
    m->cmd_len = 0;
    m->cmd_id = id;
  } else if (id != m->cmd_id) {
    ++m->protocol_errors; /* a new command cut the previous one short */
    m->cmd_len = 0;
    m->cmd_id = id;
  }
  if (m->cmd_len + len <= NRF51_SIM_MAX_CMD) {
    memcpy(m->cmd + m->cmd_len, m->pkt + 4, len);
    m->cmd_len = (uint16_t)(m->cmd_len + len);
  }
  m->cmd_open = (m->pkt[3] & MORE) != 0;
  if (m->cmd_open && viol(m, NRF51_ANSWERS_EVERY_PACKET)) {
    reply_text(m, id, "OK\r\n");
    return;
  }
  if (m->cmd_open) return; /* "Command Messages": no answer before the last packet */
  if (m->out_count) { /* an earlier answer is still unread: it stays queued, ahead */
    m->unread_at_command += m->out_count;
    if (viol(m, NRF51_DISCARDS_UNREAD)) {
      m->out_count = 0;
      m->out_pos = 0;
    }
  }
  m->pending = 1;
  m->busy_until_us = m->now_us + m->process_us;
}

void nrf51_sim_select(nrf51_sim* m, int active) {
  if (active && !m->selected) {
    m->mode = 0;
    m->pkt_pos = 0;
    m->between_packets = 0;
    if (!m->spis_ready && !m->spis_pending) { /* the SPI slave starts getting ready */
      m->spis_pending = 1;
      m->spis_ready_at_us = m->now_us + m->cs_setup_us;
    }
  } else if (!active && m->selected) {
    if (m->mode == 1 || m->mode == 2) m->spis_ready = m->spis_pending = 0; /* used up */
    if (m->mode == 1) end_packet_in(m);
    if (m->mode == 2 && m->out_pos > 0) {
      const uint8_t* p = m->out[m->out_head];
      if (m->out_pos >= 4 + (p[0] == T_ERR ? 0 : (p[3] & 0x1F))) { /* whole packet read */
        m->between_packets = (p[3] & MORE) != 0 && p[0] != T_ERR;
        m->out_head = (uint8_t)((m->out_head + 1) % NRF51_SIM_OUT_PACKETS);
        --m->out_count;
        if (m->out_count == 0) {
          m->irq_stale = m->irq_lag_us > 0;
          m->irq_low_at_us = m->now_us + m->irq_lag_us;
        }
      }
      m->out_pos = 0;
    }
  }
  m->selected = active;
}

static uint8_t first_byte(nrf51_sim* m, uint8_t mosi) {
  uint8_t miso;
  if (m->spis_pending && after(m->now_us, m->spis_ready_at_us)) m->spis_ready = 1;
  if (!m->spis_ready && !viol(m, NRF51_NO_CS_SETUP)) { /* "SPI Bus Hardware Requirements" */
    ++m->cs_early;
    ++m->not_ready;
    m->mode = 3;
    return NOT_READY;
  }
  if (busy(m)) {
    m->mode = 3;
    if (viol(m, NRF51_NEVER_NOT_READY)) return OVERREAD;
    ++m->not_ready;
    return NOT_READY;
  }
  miso = m->out_count ? m->out[m->out_head][0] : OVERREAD;
  if (mosi == T_CMD) {
    m->mode = 1;
    m->pkt[0] = mosi;
    m->pkt_pos = 1;
  } else if (m->out_count) {
    m->mode = 2;
    m->out_pos = 1;
  } else {
    ++m->overreads;
    m->mode = 3;
  }
  return miso;
}

uint8_t nrf51_sim_xfer(nrf51_sim* m, uint8_t mosi) {
  if (!m->present || !m->selected || m->in_reset) return 0xFF; /* MISO floats high */
  if (m->mode == 0) return first_byte(m, mosi);
  if (m->mode == 1) {
    if (m->pkt_pos < 20) m->pkt[m->pkt_pos++] = mosi;
    else ++m->protocol_errors;
    return OVERREAD;
  }
  if (m->mode == 2) {
    const uint8_t* p = m->out[m->out_head];
    const uint8_t total = (uint8_t)(4 + (p[0] == T_ERR ? 0 : (p[3] & 0x1F)));
    if (m->out_pos < total) return p[m->out_pos++];
    ++m->overreads;
    return OVERREAD;
  }
  return OVERREAD;
}

void nrf51_sim_reset(nrf51_sim* m, int asserted) {
  if (asserted) {
    m->in_reset = 1;
  } else if (m->in_reset) {
    m->in_reset = 0;
    boot(m);
  }
}

void nrf51_sim_set_connected(nrf51_sim* m, int connected) {
  if (connected && !m->connected) m->next_event_us = m->now_us + m->conn_interval_us;
  if (!connected) m->tx_count = 0; /* the link is gone, and what was queued for it */
  m->connected = connected;
}

void nrf51_sim_alert(nrf51_sim* m, uint16_t id, const uint8_t* payload, uint8_t len) {
  if (viol(m, NRF51_NO_ALERTS) || len > 16) return;
  ++m->alerts;
  queue_reply(m, T_ALERT, id, payload, len);
}

uint16_t nrf51_sim_central_write(nrf51_sim* m, const uint8_t* data, uint16_t len) {
  uint16_t i;
  for (i = 0; i < len && m->rx_count < NRF51_SIM_RX_FIFO; ++i) {
    m->rx[(m->rx_head + m->rx_count) % NRF51_SIM_RX_FIFO] = data[i];
    ++m->rx_count;
  }
  return i;
}
