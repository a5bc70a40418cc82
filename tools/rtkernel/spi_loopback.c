// SPDX-License-Identifier: GPL-2.0
/*
 * rtloop_spi_loopback: a software SPI controller whose wires are looped back, for the test guest.
 *
 * Debian's kernels build no software SPI controller, so /dev/spidev* cannot exist in a virtual
 * machine. This module registers one controller (its own platform device as the parent) with
 * NUM_CHIPSELECTS devices bound to spidev: every transfer copies what is sent (MOSI) to what is
 * received (MISO), as if MOSI were wired to MISO. Nothing reaches a wire and nothing is timed:
 * it exercises the kernel's SPI core, spidev and its ioctls, not a bus.
 *
 * Written for rtloop (tools/rtkernel); built against the guest kernel's headers by
 * tools/rtkernel-vm.sh. Load: insmod rtloop_spi_loopback.ko → /dev/spidevB.0 and /dev/spidevB.1.
 */
#include <linux/module.h>
#include <linux/platform_device.h>
#include <linux/slab.h>
#include <linux/spi/spi.h>
#include <linux/string.h>
#include <linux/version.h>

#define NUM_CHIPSELECTS 2
#define MAX_SPEED_HZ 50000000

static struct platform_device *parent;
static struct spi_controller *controller;

static int loopback_transfer_one(struct spi_controller *ctlr, struct spi_device *spi,
				 struct spi_transfer *xfer)
{
	if (xfer->rx_buf) {
		if (xfer->tx_buf)
			memcpy(xfer->rx_buf, xfer->tx_buf, xfer->len);
		else
			memset(xfer->rx_buf, 0, xfer->len); /* nothing sent: the looped line stays low */
	}
	return 0; /* 0: done now (no interrupt will finish it later) */
}

static int add_spidev(struct spi_controller *ctlr, u8 chip_select)
{
	struct spi_device *spi = spi_alloc_device(ctlr);
	int err;

	if (!spi)
		return -ENOMEM;
#if LINUX_VERSION_CODE >= KERNEL_VERSION(6, 3, 0)
	spi_set_chipselect(spi, 0, chip_select);
#else
	spi->chip_select = chip_select;
#endif
	spi->max_speed_hz = MAX_SPEED_HZ;
	spi->mode = SPI_MODE_0;
	spi->bits_per_word = 8;
	strscpy(spi->modalias, "rtloop-loopback", sizeof(spi->modalias));
	/* Bind spidev by name rather than pretend to be one of the chips in its id table;
	 * the SPI core frees driver_override with the device. */
	spi->driver_override = kstrdup("spidev", GFP_KERNEL);
	if (!spi->driver_override) {
		spi_dev_put(spi);
		return -ENOMEM;
	}
	err = spi_add_device(spi);
	if (err)
		spi_dev_put(spi);
	return err;
}

static int __init loopback_init(void)
{
	u8 chip_select;
	int err;

	parent = platform_device_register_simple("rtloop-spi-loopback", PLATFORM_DEVID_NONE, NULL, 0);
	if (IS_ERR(parent))
		return PTR_ERR(parent);
	controller = spi_alloc_master(&parent->dev, 0);
	if (!controller) {
		err = -ENOMEM;
		goto unregister_parent;
	}
	controller->bus_num = -1; /* the next free bus number */
	controller->num_chipselect = NUM_CHIPSELECTS;
	controller->mode_bits = SPI_CPOL | SPI_CPHA | SPI_CS_HIGH | SPI_LSB_FIRST;
	controller->bits_per_word_mask = SPI_BPW_MASK(8) | SPI_BPW_MASK(16) | SPI_BPW_MASK(32);
	controller->max_speed_hz = MAX_SPEED_HZ;
	controller->transfer_one = loopback_transfer_one;
	err = spi_register_controller(controller);
	if (err) {
		spi_controller_put(controller);
		goto unregister_parent;
	}
	for (chip_select = 0; chip_select < NUM_CHIPSELECTS; chip_select++) {
		err = add_spidev(controller, chip_select);
		if (err) {
			spi_unregister_controller(controller); /* also removes the devices added so far */
			goto unregister_parent;
		}
	}
	return 0;

unregister_parent:
	platform_device_unregister(parent);
	return err;
}

static void __exit loopback_exit(void)
{
	spi_unregister_controller(controller);
	platform_device_unregister(parent);
}

module_init(loopback_init);
module_exit(loopback_exit);
MODULE_DESCRIPTION("Software SPI controller with MOSI looped back to MISO, devices bound to spidev");
MODULE_LICENSE("GPL");
