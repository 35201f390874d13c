"""Controller links for thermocomp: OPC UA, serial, LinuxCNC and a virtual machine tool."""
