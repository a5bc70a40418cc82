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
 * A device's model can answer instead of the loop: while a process holds /dev/rtloop_spi_serve
 * open, every transfer on chip select 1 waits (up to SERVE_TIMEOUT_MS) for it. The server
 * read()s the bytes sent (one whole transfer per read, blocking until one comes) and write()s
 * the answer (exactly as many bytes), which the transfer returns as what was received. A
 * transfer the server does not answer in time, or that finds it gone meanwhile, receives 0xFF
 * bytes (MISO pulled high: no device); chip select 0 and a chip select 1 with no server stay
 * looped back. One server at a time (a second open: EBUSY).
 *
 * The server sees the whole frame sent before it answers (a device's model can answer from what
 * this very transfer carries, as a twin does in rtloop simulate); the transfer takes as long as
 * the server does. Nothing here is timed like a bus: it exercises spidev, the SPI core and a
 * device's protocol end to end (examples/jiwy_spi/fpga_server.py, docs/rtkernel-guest.md).
 *
 * Written for rtloop (tools/rtkernel); built against the guest kernel's headers by
 * tools/rtkernel-vm.sh. Load: insmod rtloop_spi_loopback.ko → /dev/spidevB.0, /dev/spidevB.1 and
 * /dev/rtloop_spi_serve.
 */
#include <linux/fs.h>
#include <linux/jiffies.h>
#include <linux/miscdevice.h>
#include <linux/module.h>
#include <linux/mutex.h>
#include <linux/platform_device.h>
#include <linux/slab.h>
#include <linux/spi/spi.h>
#include <linux/string.h>
#include <linux/uaccess.h>
#include <linux/version.h>
#include <linux/wait.h>

#define NUM_CHIPSELECTS 2
#define MAX_SPEED_HZ 50000000

static struct platform_device *parent;
static struct spi_controller *controller;

/* ------------------------------------------------------------------------------------------ */
/* Transfers on SERVED_CHIP_SELECT answered by a user-space process through a misc device.     */

#define SERVED_CHIP_SELECT 1
#define SERVE_MAX_BYTES 4096
#define SERVE_TIMEOUT_MS 2000

enum serve_state { SERVE_IDLE, SERVE_ASKED, SERVE_TAKEN, SERVE_ANSWERED };

static DEFINE_MUTEX(serve_lock); /* guards the fields below (process context only: may sleep) */
static DECLARE_WAIT_QUEUE_HEAD(serve_wait);
static bool server_open;
static enum serve_state serve_state = SERVE_IDLE;
static size_t serve_len;
static u8 serve_tx[SERVE_MAX_BYTES], serve_rx[SERVE_MAX_BYTES];

/* A wait's condition (no lock: it runs with the task state set; the waker changed them under it). */
static bool serve_is(enum serve_state wanted)
{
	return READ_ONCE(serve_state) == wanted || !READ_ONCE(server_open);
}

/* One transfer through the server: false when no server was there to ask (then loop back). */
static bool serve_transfer(struct spi_transfer *xfer)
{
	bool answered;

	if (xfer->len > SERVE_MAX_BYTES)
		return false;
	mutex_lock(&serve_lock);
	if (!server_open) {
		mutex_unlock(&serve_lock);
		return false;
	}
	if (xfer->tx_buf)
		memcpy(serve_tx, xfer->tx_buf, xfer->len);
	else
		memset(serve_tx, 0, xfer->len);
	serve_len = xfer->len;
	serve_state = SERVE_ASKED;
	mutex_unlock(&serve_lock);
	wake_up_interruptible(&serve_wait);
	wait_event_timeout(serve_wait, serve_is(SERVE_ANSWERED), msecs_to_jiffies(SERVE_TIMEOUT_MS));
	mutex_lock(&serve_lock);
	answered = serve_state == SERVE_ANSWERED;
	if (xfer->rx_buf) {
		if (answered)
			memcpy(xfer->rx_buf, serve_rx, xfer->len);
		else
			memset(xfer->rx_buf, 0xff, xfer->len); /* no answer: MISO pulled high */
	}
	serve_state = SERVE_IDLE;
	mutex_unlock(&serve_lock);
	return true;
}

static int serve_open(struct inode *inode, struct file *file)
{
	int err = 0;

	mutex_lock(&serve_lock);
	if (server_open) {
		err = -EBUSY; /* and the exchange under way, if any, goes on with the server it has */
	} else {
		server_open = true;
		serve_state = SERVE_IDLE;
	}
	mutex_unlock(&serve_lock);
	return err;
}

static int serve_release(struct inode *inode, struct file *file)
{
	mutex_lock(&serve_lock);
	server_open = false;
	mutex_unlock(&serve_lock);
	wake_up(&serve_wait); /* a transfer waiting for this server gives up now */
	return 0;
}

/* The next transfer's bytes sent (blocks until one comes; count must hold them all). */
static ssize_t serve_read(struct file *file, char __user *buf, size_t count, loff_t *pos)
{
	size_t len;
	int err;

	for (;;) {
		err = wait_event_interruptible(serve_wait, serve_is(SERVE_ASKED));
		if (err)
			return err;
		mutex_lock(&serve_lock);
		if (serve_state == SERVE_ASKED)
			break;
		mutex_unlock(&serve_lock);
	}
	len = serve_len;
	if (count < len) {
		mutex_unlock(&serve_lock);
		return -EINVAL;
	}
	/* the transfer waits for the answer: serve_tx stays as it is while it is copied */
	serve_state = SERVE_TAKEN;
	mutex_unlock(&serve_lock);
	if (copy_to_user(buf, serve_tx, len))
		return -EFAULT;
	return len;
}

/* The answer to the transfer last read: exactly its length. */
static ssize_t serve_write(struct file *file, const char __user *buf, size_t count, loff_t *pos)
{
	static u8 answer[SERVE_MAX_BYTES]; /* one server at a time: one writer */

	if (count > SERVE_MAX_BYTES)
		return -EINVAL;
	if (copy_from_user(answer, buf, count))
		return -EFAULT;
	mutex_lock(&serve_lock);
	if (serve_state != SERVE_TAKEN || count != serve_len) {
		bool late = serve_state != SERVE_TAKEN;

		mutex_unlock(&serve_lock);
		return late ? -ETIMEDOUT : -EINVAL; /* the transfer gave up waiting, or a wrong length */
	}
	memcpy(serve_rx, answer, count);
	serve_state = SERVE_ANSWERED;
	mutex_unlock(&serve_lock);
	wake_up(&serve_wait);
	return count;
}

static const struct file_operations serve_fops = {
	.owner = THIS_MODULE,
	.open = serve_open,
	.release = serve_release,
	.read = serve_read,
	.write = serve_write,
	.llseek = noop_llseek,
};

static struct miscdevice serve_device = {
	.minor = MISC_DYNAMIC_MINOR,
	.name = "rtloop_spi_serve",
	.fops = &serve_fops,
	.mode = 0600,
};

static u8 chip_select_of(struct spi_device *spi)
{
#if LINUX_VERSION_CODE >= KERNEL_VERSION(6, 3, 0)
	return spi_get_chipselect(spi, 0);
#else
	return spi->chip_select;
#endif
}

static int loopback_transfer_one(struct spi_controller *ctlr, struct spi_device *spi,
				 struct spi_transfer *xfer)
{
	if (chip_select_of(spi) == SERVED_CHIP_SELECT && serve_transfer(xfer))
		return 0;
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
	err = misc_register(&serve_device);
	if (err) {
		spi_unregister_controller(controller);
		goto unregister_parent;
	}
	return 0;

unregister_parent:
	platform_device_unregister(parent);
	return err;
}

static void __exit loopback_exit(void)
{
	misc_deregister(&serve_device);
	spi_unregister_controller(controller);
	platform_device_unregister(parent);
}

module_init(loopback_init);
module_exit(loopback_exit);
MODULE_DESCRIPTION("Software SPI controller with MOSI looped back to MISO (or chip select 1 served by a "
		   "user-space process), devices bound to spidev");
MODULE_LICENSE("GPL");
