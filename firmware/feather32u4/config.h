// config.h -- every pin, rate, size and interval of the STIP-I probe firmware, with units.
//
// Plain constants only (no Arduino headers): the portable core in src/core/ includes this file
// when it is compiled for the AVR and when it is compiled on the host for the unit tests.
// Pin numbers are Arduino (Leonardo / Feather 32u4) digital pin numbers; the AVR glue checks
// them against the Arduino names with static_assert.
#ifndef STIPI_CONFIG_H
#define STIPI_CONFIG_H

#include <stdint.h>

// ---- firmware identity (reported by GET_INFO) ---------------------------------------------
#define STIPI_FW_MAJOR 1
#define STIPI_FW_MINOR 1
#define STIPI_FW_PATCH 0

// ---- links --------------------------------------------------------------------------------
// Every link that is compiled in and open receives every frame (same bytes, same seq);
// commands are accepted from any of them. Set one to 0 with -D to leave it out of the build.
#ifndef STIPI_LINK_USB
#define STIPI_LINK_USB 1    // native USB CDC `Serial`
#endif
#ifndef STIPI_LINK_UART1
#define STIPI_LINK_UART1 1  // hardware UART `Serial1` (pins 0 RX / 1 TX); simavr's UART1
#endif
#ifndef STIPI_LINK_BLE
#define STIPI_LINK_BLE 1    // nRF51822 Bluefruit over SPI/SDEP (Nordic UART Service)
#endif
// Serial1 baud [bit/s]. 250000 is exact at F_CPU = 8 MHz (U2X, UBRR = 3, 0 % error), whereas
// 115200 would run at 111111 bit/s (-3.5 %, outside UART tolerance). 25,000 B/s at 8N1.
#define STIPI_UART1_BAUD 250000UL

// ---- pins (Feather 32u4 Bluefruit LE) -----------------------------------------------------
#define STIPI_PIN_BLE_CS 8    // nRF51822 SPI chip select (active low)
#define STIPI_PIN_BLE_IRQ 7   // nRF51822 "packet waiting" line (active high)
#define STIPI_PIN_BLE_RST 4   // nRF51822 reset (active low)
#define STIPI_PIN_LOADCELL 18 // A0 = PF7 = ADC7: FC22 output through a 2:3 divider (docs/firmware.md)
#define STIPI_PIN_VBAT 27     // A9 = D9 = PB5 = ADC12: Feather's on-board VBAT/2 divider
// LED driver transistor gate/base. D5 = PC6 = OC3A: Timer3 is free (Timer1 samples, Timer0 is
// millis/micros), so it runs 8-bit fast PWM with no prescaler = 31.25 kHz, far above any camera
// frame rate (Arduino's analogWrite would give 245 Hz at 8 MHz, which bands in camera frames).
#define STIPI_PIN_LED_PWM 5

// ---- ADC ----------------------------------------------------------------------------------
#define STIPI_ADC_BITS 10            // ATmega32u4 ADC resolution [bit]
#define STIPI_ADC_REF_MV 3300UL      // AVcc reference on the 3.3 V Feather [mV]
#define STIPI_VBAT_DIVIDER 2UL       // VBAT is read through a 1:2 divider on the Feather
// Oversampling (src/core/oversample.h): up to STIPI_OVERSAMPLE_MAX conversions back to back from
// each sample instant, averaged; fewer at high rates so that they fit the period (16 up to
// 486 Hz, 8 up to 881 Hz, 4 above). A conversion is 13 ADC clocks = 104 us at 125 kHz;
// the budget adds the interrupt latency.
#define STIPI_OVERSAMPLE_MAX 16      // power of two, <= 16
#define STIPI_ADC_CONV_BUDGET_US 115 // time reserved per conversion [us]
#define STIPI_ADC_CONV_PERIOD_US 115 // start-to-start of chained conversions [us] (114.5 in simavr)
#define STIPI_ADC_MARGIN_US 100      // left free per period for interrupt latency [us]
// The supply reading is chained after a sample only if its conversion then ends this long before
// the next sample instant (oversample.h supply_fits); otherwise it waits for a later sample.
#define STIPI_ADC_SUPPLY_SLACK_US 40 // [us]
// Extra bits on the wire: 0 keeps SAMPLES.adc in 10-bit counts (the averaged mean, rounded;
// calibrations and the host's load-cell model stay valid); 2 sends 12-bit counts (sum of 16
// conversions / 4) and GET_INFO reports adc_bits = 12 (recalibrate: zero and span change x4).
#ifndef STIPI_ADC_EXTRA_BITS
#define STIPI_ADC_EXTRA_BITS 0
#endif
#define STIPI_ADC_OUT_BITS (STIPI_ADC_BITS + STIPI_ADC_EXTRA_BITS)  // SAMPLES.adc bits

// ---- FC22 supply (ratiometric correction) -------------------------------------------------
// The FC22 output is ratiometric to its 5 V supply (USB), the ADC to the 3.3 V regulator. Wire
// the 5 V rail through two equal resistors (e.g. 10 k / 10 k: 2.5 V = 776 counts) to an analog
// pin and set STIPI_PIN_SUPPLY5 to it (e.g. -DSTIPI_PIN_SUPPLY5=19 for A1): every sample is then
// scaled by nominal/measured supply (both voltages cancel) and STATUS.supply_mv reports the
// 5 V rail. Left at -1 (not wired), samples are uncorrected, STATUS.supply_mv is VBAT (A9) and
// STATUS.flags bit 4 says "force not supply-corrected".
#ifndef STIPI_PIN_SUPPLY5
#define STIPI_PIN_SUPPLY5 -1
#endif
#define STIPI_SUPPLY5_DIVIDER 2UL          // 5 V rail / voltage at the pin
#define STIPI_SUPPLY5_NOMINAL_MV 5000UL    // the supply the calibration refers to [mV]
#define STIPI_SUPPLY5_MIN_MV 4000UL        // outside this range the reading is not trusted
#define STIPI_SUPPLY5_MAX_MV 5600UL        // (no correction, flag set) [mV]

// ---- sampling -----------------------------------------------------------------------------
#define STIPI_DEFAULT_RATE_HZ 100    // sample rate after boot [Hz]
#define STIPI_MAX_RATE_HZ 1000       // SET_RATE upper limit [Hz] (protocol: 1..1000)
// SET_RATE lower limit [Hz]: SAMPLES.period_us is a u16, so the period must be <= 65535 us,
// i.e. rate >= 16 Hz (62500 us). Lower rates are refused with status 2 (docs/firmware.md).
#define STIPI_MIN_RATE_HZ 16
#define STIPI_BATCH_SIZE 10          // samples per SAMPLES frame (1..24); 10 -> 39 B on the wire
#define STIPI_RING_CAPACITY 128      // ISR -> main ring buffer [samples], power of two (<= 128)
#define STIPI_TARE_SAMPLES 16        // samples averaged by TARE (power of two)

// ---- timing -------------------------------------------------------------------------------
#define STIPI_HEARTBEAT_PERIOD_US 500000UL   // STATUS period [us]; protocol requires <= 1 s
// Watchdog: a main-loop pass takes < 1 ms; a loop stuck for the first period marks "watchdog"
// in RAM from the watchdog interrupt and the second period resets the MCU (1 s in all).
#ifndef STIPI_WATCHDOG
#define STIPI_WATCHDOG 1
#endif
#define STIPI_WATCHDOG_PERIOD_MS 500         // WDTO_500MS: interrupt after it, reset after 2x
#define STIPI_LINK_READ_BUDGET 32            // bytes read per link per loop pass [B]
#define STIPI_USB_TX_RING 160                // USB CDC frames waiting for the endpoint [B]
#define STIPI_UART1_TX_RING 128              // Serial1 frames waiting for its TX buffer [B]

// ---- BLE / SDEP ---------------------------------------------------------------------------
#define STIPI_SDEP_CS_SETUP_US 100           // wait after asserting CS [us] (hardware.md)
// A command without an answer by then failed [us]. The module's own longest wait is the 200 ms
// a UART TX waits for FIFO room before it answers ERROR (hardware.md), plus its processing
// (a few ms); 500 ms leaves 300 ms (2.5x the wait) of margin, so a slow answer is never taken
// for a dead module and no new command goes over an answer still coming. With the flow
// control below a TX never waits for room at all.
#define STIPI_SDEP_TIMEOUT_US 500000UL
#define STIPI_SDEP_PACKETS_PER_POLL 2        // SPI transactions per loop pass (~0.2 ms each)
#define STIPI_BLE_RESET_PULSE_US 20000UL     // RST low time [us]
#define STIPI_BLE_BOOT_US 1000000UL          // wait after reset before the first command [us]
#define STIPI_BLE_PROBE_ATTEMPTS 2           // "ATE=0" attempts that nothing answered (not even
                                             // 0xFE, "busy") before the module counts as absent
#define STIPI_BLE_BOOT_MAX_US 10000000UL     // still answering only 0xFE this long after its
                                             // reset: the module is reset again [us]
#define STIPI_BLE_RETRY_MIN_US 1000000UL     // absent: reset and probe again after this [us],
#define STIPI_BLE_RETRY_MAX_US 32000000UL    // doubling up to this, for as long as we run [us]
#define STIPI_BLE_SILENT_TO_REPROBE 3        // commands in a row without any answer: the module
                                             // restarted or hung; probe it again
#define STIPI_BLE_CONN_POLL_US 1000000UL     // AT+GAPGETCONN interval [us]
#define STIPI_BLE_RX_POLL_US 20000UL         // BLE UART RX poll interval while connected [us]
#define STIPI_BLE_RX_FIFO 64                 // received BLE bytes buffered [B]
#define STIPI_BLE_TX_RING 224                // whole frames waiting for BLE [B]
#define STIPI_BLE_FIFO_POLL_US 20000UL       // ask AT+BLEUARTFIFO=TX again while short of room [us]
#define STIPI_BLE_TX_CHUNK 128               // most bytes in one UART TX command [B]

// ---- EEPROM -------------------------------------------------------------------------------
#define STIPI_EEPROM_CAL_ADDR 0              // first byte of the two calibration slots
#define STIPI_EEPROM_SIZE 1024               // ATmega32u4 EEPROM [B]

#endif  // STIPI_CONFIG_H
